"""Guessed focal length: ``rotonly run`` against ``colmap mapper`` on a database whose focal
COLMAP's front end only guessed (issue 20's time and accuracy targets).

Usage: python scripts/bench/guessed_focal.py --scene DATA/strecha/fountain-P11
                                       [--database DB] [--camera-per-image] [--rounds N]
                                       [-o RESULTS_DIR] [--results-md docs/results.md]

Both tools get the same database (``SCENE/database_guessed_focal.db`` by default: COLMAP 3.8's
CLI defaults, ``SIMPLE_RADIAL``, f guessed as 1.2 x the image size, ``prior_focal_length =
0``; with ``--camera-per-image`` rewritten with a copy of the camera per image, as COLMAP's
feature extractor leaves a database by default), the mapper on a private copy, in N
alternating rounds (tool_runs.alternating_runs: a slow stretch of the shared machine
falls on both alike), timed as whole processes:

* ``rotonly -q run DB -o OUT`` (default settings: ``--intrinsics auto`` calibrates the guess);
* ``colmap mapper`` (the Debian package's CLI: incremental mapping with its bundle adjustment
  refining the focal, default settings, all threads).

Scored by one evaluator (``rotonly_cli.evaluation.quality.evaluate`` against
``SCENE/gt_dense_cameras``) on the last round's outputs, with the focal each tool ended with.
The ratio of the median wall times is the issue's measure (target <= 0.3x).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from strecha_tools import fmt
from tool_runs import (
    _round_dir,
    alternating_runs,
    byte_compile_rotonly,
    evaluate_scene,
    reconstruction_scene,
    rotonly_run_command,
)

from rotonly_cli.bench import results_md
from rotonly_cli.bench.common import code_version
from rotonly_cli.io import colmap, detect, openmvg

TARGET_RATIO = 0.3


def colmap_mapper_command(colmap: str, database: Path, images: Path, out: Path) -> list[str]:
    return [colmap, "mapper", "--database_path", str(database), "--image_path", str(images),
            "--output_path", str(out)]


def colmap_result(out: Path, gt):
    """The largest model colmap mapper wrote under ``out`` (sparse/N), evaluated, and its focal."""
    import pycolmap

    models = [pycolmap.Reconstruction(str(d)) for d in sorted(out.iterdir()) if (d / "cameras.bin").is_file()]
    if not models:
        return None, None
    best = max(models, key=lambda r: r.num_reg_images())
    focal = [float(c.mean_focal_length()) for c in best.cameras.values()]
    return evaluate_scene("colmap mapper", gt, reconstruction_scene(best), None), focal


def rotonly_result(out: Path, gt):
    report = json.loads((out / "reports" / "intrinsics.json").read_text())
    focal = [camera["end"]["focal_px"] for camera in report["cameras"].values()]
    return evaluate_scene("rotonly run", gt, openmvg.read_sfm_data(out / "sfm_data.json"), None), focal, report


def camera_per_image(database: Path, out: Path) -> Path:
    """``database`` written to ``out`` with every image on its own copy of its camera (what
    ``colmap feature_extractor`` makes without ``--ImageReader.single_camera``)."""
    from dataclasses import replace

    scene = colmap.read_database(database)
    intrinsics, views = {}, {}
    for number, (view_id, view) in enumerate(sorted(scene.views.items()), start=1):
        intrinsics[number] = replace(scene.intrinsics[view.intrinsics_id], id=number)
        views[view_id] = replace(view, intrinsics_id=number)
    colmap.write_database(out, replace(scene, intrinsics=intrinsics, views=views))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True, help="Strecha scene folder (gt_dense_cameras/, images/)")
    parser.add_argument("--database", type=Path, default=None,
                        help="the database (default: SCENE/database_guessed_focal.db)")
    parser.add_argument("--camera-per-image", action="store_true",
                        help="give both tools the database with a camera per image (COLMAP's default)")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    parser.add_argument("--colmap", default="colmap", help="the colmap executable (default: colmap on PATH)")
    parser.add_argument("-o", "--output", type=Path, default=Path("bench_results/guessed_focal"),
                        help="results folder (replaced atomically)")
    parser.add_argument("--results-md", type=Path, default=None,
                        help="also write the table into this file's `guessed-focal` section (docs/results.md)")
    args = parser.parse_args(argv)
    scene = args.scene.resolve()
    database = (args.database or scene / "database_guessed_focal.db").resolve()
    if args.rounds < 1:
        parser.error("--rounds: must be >= 1")
    if not database.is_file():
        parser.error(f"no database {database}")
    if shutil.which(args.colmap) is None:
        parser.error(f"--colmap: {args.colmap} not found (Debian: apt-get install colmap)")
    results_dir = args.output.resolve()
    gt = detect.read_ground_truth(scene)
    byte_compile_rotonly()
    load_at_start = os.getloadavg()[0]
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="guessed_focal.") as tmp:
        work = Path(tmp)
        given = database
        if args.camera_per_image:
            database = camera_per_image(given, work / "camera_per_image.db")

        def mapper_run(k: int) -> list[str]:
            folder = _round_dir(work, "colmap", k)
            (folder / "sparse").mkdir(parents=True)
            shutil.copyfile(database, folder / "database.db")
            return colmap_mapper_command(args.colmap, folder / "database.db", scene / "images", folder / "sparse")

        def rotonly_run(k: int) -> list[str]:  # rotonly never writes into its input: no copy
            folder = _round_dir(work, "rotonly", k)
            folder.mkdir()
            return rotonly_run_command(database, folder / "out")

        runs = alternating_runs({"rotonly": rotonly_run, "colmap": mapper_run}, args.rounds)
        last = args.rounds - 1
        ours, ours_focal, intrinsics_report = rotonly_result(work / f"rotonly_{last}" / "out", gt)
        theirs, theirs_focal = colmap_result(work / f"colmap_{last}" / "sparse", gt)
    times = {name: [t for t, _ in values] for name, values in runs.items()}
    ratio = float(np.median(times["rotonly"]) / np.median(times["colmap"]))
    per_round = np.array(times["rotonly"]) / np.array(times["colmap"])
    lines = ["| tool | wall time median (s) | min-max (s) | rotation error mean / median (deg) | "
             "registered | focal (px) |", "|---|---|---|---|---|---|"]
    for name, key, result, focal in (("rotonly run", "rotonly", ours, ours_focal),
                                     ("colmap mapper", "colmap", theirs, theirs_focal)):
        t = times[key]
        score = "failed" if result is None or result.error else (
            f"{fmt(result.rotation_mean_deg)} / {fmt(result.rotation_median_deg)}")
        registered = "–" if result is None else f"{result.num_registered}/{result.num_gt}"
        lines.append(f"| {name} | {np.median(t):.2f} | {min(t):.2f}-{max(t):.2f} | {score} | {registered} | "
                     f"{', '.join(f'{f:.1f}' for f in focal or [])} |")
    verdict = "met" if ratio <= TARGET_RATIO else "NOT met"
    warnings = intrinsics_report.get("warnings", [])
    body = "\n".join(lines) + (
        f"\n\nrotonly / colmap mapper, ratio of the median wall times over {args.rounds} alternating rounds: "
        f"**{ratio:.2f}x** (per round {per_round.min():.2f}-{per_round.max():.2f}x; target <= {TARGET_RATIO}x: "
        f"{verdict}). rotonly's warnings: {'; '.join(warnings) if warnings else 'none'}.\n\n"
        f"Database {given.name}{' with a camera per image' if args.camera_per_image else ''} ({scene.name}); "
        f"load average (1 min) at start / end {load_at_start:.1f} / "
        f"{os.getloadavg()[0]:.1f}; code {code_version()}; {time.perf_counter() - start:.0f} s in all.")
    print(body)
    payload = {"database": str(given), "camera_per_image": args.camera_per_image, "rounds": args.rounds,
               "times_s": times, "ratio_of_medians": ratio,
               "rotonly": vars(ours), "colmap": None if theirs is None else vars(theirs),
               "focal_px": {"rotonly": ours_focal, "colmap": theirs_focal}, "rotonly_warnings": warnings,
               "code_version": code_version()}
    from rotonly_cli.io.atomic import staging_dir

    results_dir.parent.mkdir(parents=True, exist_ok=True)
    with staging_dir(results_dir) as out:
        (out / "results.json").write_text(json.dumps(payload, indent=1, default=float) + "\n")
        (out / "table.md").write_text(f"# Guessed focal: rotonly against colmap mapper\n\n{body}\n")
    section = "guessed-focal-per-image" if args.camera_per_image else "guessed-focal"
    title = "Guessed focal, a camera per image" if args.camera_per_image else "Guessed focal"
    results_md.record(args.results_md, section, f"{title}: rotonly against colmap mapper",
                      results_md.command_line("python scripts/bench/guessed_focal.py", argv), body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
