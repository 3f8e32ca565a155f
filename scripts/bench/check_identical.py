#!/usr/bin/env python3
"""Check that ``rotonly run`` still writes the same bytes as a reference run.

Every input of ROOT's Strecha scenes (``<scene>/*.db`` and ``<scene>/openmvg/sfm_data.json``)
is run with the current code into a scratch folder, and ``sfm_data.json``, ``view_graph.json``
and every file of ``sparse/`` are compared byte for byte with ``REF/<name>/``. ``--write-ref`` makes the
references instead (run it once with the code to compare against).

    python scripts/bench/check_identical.py --root DATA/strecha --ref REF_DIR --write-ref
    python scripts/bench/check_identical.py --root DATA/strecha --ref REF_DIR

The input paths are written into sfm_data.json (``root_path``), so give the same ``--root``
both times. Exit code 0 when every input matches, 1 otherwise.
"""

from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUN = "from rotonly_cli.cli import console_main; console_main()"


def inputs(root: Path, scenes: list[str] | None) -> dict[str, Path]:
    """name -> input path: ``<scene>_db`` for database.db, ``<scene>_<rest>`` for
    database_<rest>.db, ``<scene>_openmvg`` for openmvg/sfm_data.json."""
    found: dict[str, Path] = {}
    for scene in sorted(p for p in root.iterdir() if p.is_dir()):
        if scenes and scene.name not in scenes:
            continue
        for db in sorted(scene.glob("*.db")):
            suffix = "db" if db.stem == "database" else db.stem.removeprefix("database_")
            found[f"{scene.name}_{suffix}"] = db
        sfm_data = scene / "openmvg" / "sfm_data.json"
        if sfm_data.is_file():
            found[f"{scene.name}_openmvg"] = sfm_data
    return found


def run(input_path: Path, out_dir: Path) -> None:
    subprocess.run([sys.executable, "-c", RUN, "-q", "run", str(input_path), "-o", str(out_dir)], check=True,
                   stdout=subprocess.DEVNULL)


def compared_files(out_dir: Path) -> list[Path]:
    """sfm_data.json, view_graph.json and every file of sparse/, relative to ``out_dir``
    (the reports hold run times, run.log time stamps: those are not compared)."""
    sparse = sorted(p.relative_to(out_dir) for p in (out_dir / "sparse").rglob("*") if p.is_file())
    return [Path("sfm_data.json"), Path("view_graph.json"), *sparse]


def differences(reference: Path, current: Path) -> list[str]:
    names = sorted(set(compared_files(reference)) | set(compared_files(current)))
    problems = []
    for name in names:
        a, b = reference / name, current / name
        if not a.is_file() or not b.is_file():
            problems.append(f"{name}: only in {'current' if b.is_file() else 'reference'}")
        elif not filecmp.cmp(a, b, shallow=False):
            problems.append(f"{name}: bytes differ")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="folder of Strecha scenes")
    parser.add_argument("--ref", type=Path, required=True, help="folder of reference outputs (<name>/)")
    parser.add_argument("--scenes", nargs="*", default=None, help="scene folder names (default: all)")
    parser.add_argument("--write-ref", action="store_true", help="write the references instead of comparing")
    args = parser.parse_args(argv)
    root = args.root.resolve()
    todo = inputs(root, args.scenes)
    if not todo:
        parser.error(f"no inputs under {root}")
    failed = 0
    with tempfile.TemporaryDirectory(prefix="check_identical.") as scratch:
        for name, input_path in todo.items():
            start = time.perf_counter()
            if args.write_ref:
                run(input_path, args.ref / name)
                print(f"{name}: reference written ({time.perf_counter() - start:.1f} s)")
                continue
            if not (args.ref / name).is_dir():
                print(f"{name}: no reference in {args.ref}")
                failed += 1
                continue
            out_dir = Path(scratch) / name
            run(input_path, out_dir)
            problems = differences(args.ref / name, out_dir)
            failed += bool(problems)
            count = len(compared_files(out_dir))
            verdict = "identical" if not problems else "DIFFERENT: " + "; ".join(problems)
            print(f"{name}: {count} files {verdict} ({time.perf_counter() - start:.1f} s)")
    if not args.write_ref:
        print(f"{len(todo) - failed} of {len(todo)} inputs identical")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
