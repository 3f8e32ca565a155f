#!/usr/bin/env python
"""Probe: does rotonly hold on a drone survey, nadir strips over flat or hilly ground?
Simulated with ``rotonly_cli.simulation.user_cameras.simulate_survey`` (0.5 px noise, 5 % wrong
matches, pairs verified by COLMAP's two-view geometry estimator; over flat ground every pair
is PLANAR_OR_PANORAMIC and the focal trades for the flying height), then `rotonly run`
in-process with the camera known (its principal point at the image centre, as an EXIF camera
arrives) and with COLMAP's guess (``--focal-factors``, no prior focal). With ``--mapper`` also
pycolmap's global mapper (GLOMAP; a known camera held fixed, a guess refined by its bundle
adjustment) on the same database, as a reference. One row per
run: views registered, mean rotation error after rotation alignment, position error after
similarity alignment (GT units: metres), the focal it ends at, what the intrinsics stage
decided, and the wall time.

    python scripts/research/probe_survey.py [--seeds 2] [--strips 3] [--per-strip 8] \
        [--relief 0 10] [--points 30000] [--focal-factors 1.2] [--mapper]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _errors(estimate, problem) -> tuple[float, float]:
    """(mean rotation error, mean position error) of a posed SfMScene against the survey's
    ground truth, by the project's one evaluator (evaluation.quality.evaluate)."""
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.simulation import user_cameras

    report = evaluate(user_cameras.gt_scene(problem), estimate)
    position = float("nan") if report.position_error is None else report.position_error.mean
    return report.rotation_error_deg.mean, position


def run_rotonly(problem, camera) -> dict:
    """One simulated survey through `rotonly run` with ``camera`` as the input's."""
    import rotonly_cli
    from rotonly_cli.simulation import user_cameras

    scene = user_cameras.user_scene(problem, camera, user_cameras.verified_pairs(problem))
    start = time.perf_counter()
    result = rotonly_cli.run(scene, progress=False)
    seconds = time.perf_counter() - start
    rotation, position = _errors(result.scene, problem)
    report = result.reports["intrinsics"]["cameras"][str(camera.id)]
    return {"registered": len(result.rotations), "rotation_deg": rotation, "position": position,
            "focal_px": report["end"]["focal_px"], "calibrated": report.get("calibrated") or "kept",
            "seconds": seconds}


def run_mapper(problem, true_intrinsics: bool) -> dict:
    """pycolmap's global mapper on the survey written as a COLMAP database (``true_intrinsics``:
    the camera known and held fixed; else the guess, refined)."""
    import pycolmap

    from rotonly_cli.io.colmap.model import scene_from_reconstruction
    from rotonly_cli.simulation import user_cameras

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        database = user_cameras.write_inputs(folder, problem, formats=("colmap",),
                                             true_intrinsics=true_intrinsics)["colmap"]
        (folder / "images").mkdir()
        (folder / "models").mkdir()
        options = pycolmap.GlobalPipelineOptions()
        options.random_seed = options.mapper.random_seed = 0
        if true_intrinsics:  # a known camera stays fixed, as in rotonly; a guess is refined
            adjustment = options.mapper.bundle_adjustment
            adjustment.refine_focal_length = adjustment.refine_principal_point = False
            adjustment.refine_extra_params = False
        start = time.perf_counter()
        models = pycolmap.global_mapping(database, folder / "images", folder / "models", options)
        seconds = time.perf_counter() - start
    if not models:
        return {"registered": 0, "rotation_deg": float("nan"), "position": float("nan"), "focal_px": float("nan"),
                "calibrated": "-", "seconds": seconds}
    reconstruction = max(models.values(), key=lambda r: r.num_reg_images())
    rotation, position = _errors(scene_from_reconstruction(reconstruction), problem)
    [camera] = reconstruction.cameras.values()
    return {"registered": reconstruction.num_reg_images(), "rotation_deg": rotation, "position": position,
            "focal_px": float(camera.params[0]), "calibrated": "BA", "seconds": seconds}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--strips", type=int, default=3)
    parser.add_argument("--per-strip", type=int, default=8)
    parser.add_argument("--relief", type=float, nargs="+", default=[0.0, 10.0], help="ground relief (m)")
    parser.add_argument("--points", type=int, default=30000)
    parser.add_argument("--focal-factors", type=float, nargs="*", default=[1.2])
    parser.add_argument("--mapper", action="store_true", help="pycolmap's global mapper on the same inputs")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    from rotonly_cli.simulation import user_cameras

    print("| relief (m) | seed | camera | method | registered | rotation (deg) | position (m) | focal at end (px) "
          "| intrinsics | time (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for relief in args.relief:
        for seed in range(args.seeds):
            problem = user_cameras.simulate_survey(seed, strips=args.strips, per_strip=args.per_strip, relief=relief,
                                                   num_points=args.points)
            views = len(problem.gt_poses)
            for factor in [None, *args.focal_factors]:
                camera = problem.true
                if factor is not None:
                    camera = replace(camera, params=np.array([camera.params[0] * factor, *camera.params[1:]]),
                                     prior_focal=False)
                case = replace(problem, guessed=camera)
                rows = [("rotonly", run_rotonly(case, camera))]
                if args.mapper:
                    rows.append(("global mapper", run_mapper(case, factor is None)))
                for method, row in rows:
                    print(f"| {relief:g} | {seed} | {'known' if factor is None else f'guess x{factor:g}'} | {method} | "
                          f"{row['registered']}/{views} | {row['rotation_deg']:.4f} | {row['position']:.4f} | "
                          f"{row['focal_px']:.1f} ({problem.true.params[0]:.0f}) | {row['calibrated']} | "
                          f"{row['seconds']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
