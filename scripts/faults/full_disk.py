#!/usr/bin/env python3
"""`rotonly run` onto a full disk (issue 21): OUT's parent, then $TMPDIR, on a small tmpfs.

For every size the run must either finish (exit 0, a complete workspace) or stop with one
line and exit 1, leaving nothing on the small file system, and no process of it alive 3 s
after it ended (processes.py: each run a process group, every wait bounded). Needs root (it
mounts tmpfs).

    sudo python scripts/faults/full_disk.py [--input DB] [--sizes 64k 256k 1m 2m 4m]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import processes

REPOSITORY = processes.REPOSITORY
DEFAULT_INPUT = REPOSITORY / "data_fixtures" / "herzjesu_p8" / "database.db"
DEFAULT_SIZES = ["64k", "256k", "512k", "1m", "1536k", "2m", "3m", "4m", "6m", "8m", "16m"]


def run(input_path: Path, out: Path, tmpdir: Path | None = None) -> tuple[int | None, list[str], list[int]]:
    """(exit code, None if the run hung; its stderr lines; its processes alive 3 s after it ended)."""
    outcome = processes.finish(processes.start(["-q", "run", input_path, "-o", out],
                                               tmpdir or Path(tempfile.gettempdir())), timeout=900)
    return outcome.code, outcome.stderr.strip().splitlines(), outcome.orphans


def mounted(folder: Path, size: str):
    folder.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], check=True)
    return folder


def complete(out: Path) -> bool:
    """Every output there and readable in full (a writer that ignored a full disk would
    have left a short file)."""
    from rotonly_cli.errors import InputError
    from rotonly_cli.io.colmap.model_check import check_model
    from rotonly_cli.io.openmvg import read_sfm_data
    from rotonly_cli.io.workspace import load_state

    try:
        check_model(out / "sparse")
        read_sfm_data(out / "sfm_data.json")
        load_state(out)
    except InputError as exc:
        print(f"  incomplete output: {exc}")
        return False
    return True


def verdict(code: int | None, lines: list[str], left: list[str], out: Path, orphans: list[int]) -> bool:
    if orphans:
        return False
    if code == 0:
        return complete(out)
    return code == 1 and len(lines) == 1 and lines[0].startswith("error: ") and not left


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=DEFAULT_INPUT)
    parser.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES)
    args = parser.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="rotonly-full-disk-"))
    failures = 0
    try:
        for where in ("OUT's parent", "$TMPDIR"):
            for k, size in enumerate(args.sizes):
                small = mounted(root / f"small{where[0]}{k}", size)
                try:
                    if where == "$TMPDIR":
                        (small / "filler").write_bytes(b"")
                        subprocess.run(["dd", "if=/dev/zero", f"of={small / 'filler'}", "bs=4k"], capture_output=True)
                        out = root / f"out{k}"
                        code, lines, orphans = run(args.input, out, tmpdir=small)
                        left = sorted(p.name for p in small.iterdir() if p.name != "filler")
                    else:
                        out = small / "deep" / "out"
                        code, lines, orphans = run(args.input, out)
                        left = [] if code == 0 else sorted(p.name for p in small.iterdir())
                    clean = verdict(code, lines, left, out, orphans)
                    failures += not clean
                    print(f"{where} on a {size:>5} tmpfs: exit {code}, {lines[-1] if lines else 'no message'}, "
                          f"left {left or 'nothing'}, {len(orphans)} orphans"
                          + ("" if clean else "  <-- NOT CLEAN " + str(lines[:3])))
                finally:
                    subprocess.run(["umount", str(small)], check=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"{2 * len(args.sizes)} runs, {failures} not clean")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
