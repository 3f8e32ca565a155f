#!/usr/bin/env python3
"""Check that ``rotonly run`` still writes the same bytes as a reference run.

Every input of ROOT's Strecha scenes (``<scene>/*.db`` and ``<scene>/openmvg/sfm_data.json``)
is run with the current code into a scratch folder, and ``sfm_data.json``, ``view_graph.json``
and every file of ``sparse/`` are compared byte for byte with ``REF/<name>/``. ``--write-ref`` makes the
references instead (run it once with the code to compare against). ``--against-fixed``
compares each default run with the same run under ``--intrinsics fixed`` instead (no
references: issue 20's check that ``auto`` leaves calibrated cameras alone).

    python scripts/bench/check_identical.py --root DATA/strecha --ref REF_DIR --write-ref
    python scripts/bench/check_identical.py --root DATA/strecha --ref REF_DIR
    python scripts/bench/check_identical.py --root DATA/strecha --against-fixed --kinds db openmvg

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


def inputs(root: Path, scenes: list[str] | None, kinds: list[str] | None = None) -> dict[str, Path]:
    """name -> input path: ``<scene>_db`` for database.db, ``<scene>_<rest>`` for
    database_<rest>.db, ``<scene>_openmvg`` for openmvg/sfm_data.json; ``kinds``: only those
    suffixes (``db``, ``openmvg``, ``guessed_focal`` ...)."""
    found: dict[str, Path] = {}
    for scene in sorted(p for p in root.iterdir() if p.is_dir()):
        if scenes and scene.name not in scenes:
            continue
        candidates = {("db" if db.stem == "database" else db.stem.removeprefix("database_")): db
                      for db in sorted(scene.glob("*.db"))}
        if (scene / "openmvg" / "sfm_data.json").is_file():
            candidates["openmvg"] = scene / "openmvg" / "sfm_data.json"
        for suffix, path in candidates.items():
            if not kinds or suffix in kinds:
                found[f"{scene.name}_{suffix}"] = path
    return found


def run(input_path: Path, out_dir: Path, *options: str) -> None:
    subprocess.run([sys.executable, "-c", RUN, "-q", "run", str(input_path), "-o", str(out_dir), *options],
                   check=True, stdout=subprocess.DEVNULL)


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
    parser.add_argument("--ref", type=Path, default=None, help="folder of reference outputs (<name>/)")
    parser.add_argument("--scenes", nargs="*", default=None, help="scene folder names (default: all)")
    parser.add_argument("--kinds", nargs="*", default=None,
                        help="input kinds: db, openmvg, or the <rest> of database_<rest>.db (default: all)")
    parser.add_argument("--write-ref", action="store_true", help="write the references instead of comparing")
    parser.add_argument("--against-fixed", action="store_true",
                        help="compare the default run with the run under --intrinsics fixed (no references)")
    args = parser.parse_args(argv)
    if args.ref is None and not args.against_fixed:
        parser.error("--ref is needed unless --against-fixed")
    root = args.root.resolve()
    todo = inputs(root, args.scenes, args.kinds)
    if not todo:
        parser.error(f"no inputs under {root}")
    failed = 0
    with tempfile.TemporaryDirectory(prefix="check_identical.") as scratch:
        for name, input_path in todo.items():
            start = time.perf_counter()
            if args.against_fixed:
                run(input_path, Path(scratch) / f"{name}.fixed", "--intrinsics", "fixed")
                run(input_path, Path(scratch) / name)
                problems = differences(Path(scratch) / f"{name}.fixed", Path(scratch) / name)
                failed += bool(problems)
                verdict = "identical to --intrinsics fixed" if not problems else "DIFFERENT: " + "; ".join(problems)
                print(f"{name}: {len(compared_files(Path(scratch) / name))} files {verdict} "
                      f"({time.perf_counter() - start:.1f} s)", flush=True)
                continue
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
