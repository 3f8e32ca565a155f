#!/usr/bin/env python
"""Probe: does rotonly hold on a panorama from a tripod, every pair a pure rotation?
Simulated with ``rotonly_cli.simulation.user_cameras.simulate_panorama`` (views turned about
one centre, 0.3 px noise, 5 % wrong matches, pairs verified by COLMAP's two-view geometry
estimator), then `rotonly run` in-process. Two tables:

* per seed: views registered, rotation error, the spread of the centres, the edge kinds, and
  the run with the focal guessed (``--focal-factors``: COLMAP's guess without EXIF) with the
  focal it ends at;
* the PURE_ROTATION ratio ρ of every edge against its threshold (IdentificationOptions
  .pure_rotation_ratio_sigmas): how many edges pass a fixed 3 or 6 and the threshold at
  z = 2 / 2.5 / 3, with few matches (``--points``) as with many.

    python scripts/research/probe_panorama.py [--seeds 3] [--views 24] [--step-deg 15] \
        [--points 8000 1500] [--focal-factors 0.7 1.2]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace

import numpy as np


def run_panorama(seed: int, views: int, step_deg: float, points: int, focal_factor: float | None = None) -> dict:
    """One simulated panorama through `rotonly run`: registered, rotation error (deg), centre
    spread, edge kinds, the final focal, and (ρ, matches) of every identified edge."""
    import rotonly_cli
    from rotonly_cli.geometry import alignment
    from rotonly_cli.simulation import user_cameras

    problem = user_cameras.simulate_panorama(seed, num_views=views, step_deg=step_deg, num_points=points,
                                             min_shared=20)
    camera = problem.true
    if focal_factor is not None:
        camera = replace(camera, params=np.array([camera.params[0] * focal_factor, *camera.params[1:]]),
                         prior_focal=False)
        problem = replace(problem, guessed=camera)
    scene = user_cameras.user_scene(problem, camera, user_cameras.verified_pairs(problem))
    start = time.perf_counter()
    result = rotonly_cli.run(scene, progress=False)
    seconds = time.perf_counter() - start
    ids = sorted(result.rotations)
    errors = alignment.rotation_errors_after_alignment(np.array([result.rotations[v] for v in ids]),
                                                       np.array([problem.gt_poses[v].R_cam_from_world for v in ids]))[0]
    centres = np.array([result.centers[v] for v in sorted(result.centers)])
    kinds: dict[str, int] = {}
    for edge in result.graph.edges:
        kind = edge.scene_kind or "not identified"
        kinds[kind] = kinds.get(kind, 0) + 1
    ratios = [(edge.pure_rotation_ratio, edge.num_inliers) for edge in result.graph.edges
              if np.isfinite(edge.pure_rotation_ratio)]
    focal = result.reports["intrinsics"]["cameras"][str(camera.id)]["end"]["focal_px"]
    return {"registered": len(ids), "views": views, "rotation_deg": float(errors.mean()),
            "centre_spread": float(np.ptp(centres, axis=0).max()) if len(centres) else float("nan"),
            "kinds": kinds, "focal_px": focal, "true_focal_px": float(problem.true.params[0]),
            "ratios": ratios, "seconds": seconds}


def threshold_counts(ratios: np.ndarray, counts: np.ndarray) -> dict[str, int]:
    """How many pure-rotation edges exceed each candidate threshold (ρ, matches)."""
    from rotonly_cli.geometry import identification
    from rotonly_cli.options import IdentificationOptions

    out = {"fixed 3": int(np.sum(ratios >= 3.0)), "fixed 6": int(np.sum(ratios >= 6.0))}
    for z in (2.0, 2.5, 3.0):
        options = IdentificationOptions(pure_rotation_ratio_sigmas=z)
        limit = identification.pure_rotation_ratio_thresholds(counts, options)
        out[f"z = {z:g}"] = int(np.sum(ratios >= limit))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--step-deg", type=float, default=15.0)
    parser.add_argument("--points", type=int, nargs="+", default=[8000, 1500])
    parser.add_argument("--focal-factors", type=float, nargs="*", default=[0.7, 1.2])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)

    print("| points | seed | focal | registered | rotation (deg) | centre spread | kinds | focal at end (px) "
          "| time (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for points in args.points:
        ratios, counts = [], []
        for seed in range(args.seeds):
            for factor in [None, *args.focal_factors]:
                row = run_panorama(seed, args.views, args.step_deg, points, factor)
                if factor is None:
                    ratios += [r for r, _ in row["ratios"]]
                    counts += [m for _, m in row["ratios"]]
                kinds = ", ".join(f"{k} {n}" for k, n in sorted(row["kinds"].items()))
                print(f"| {points} | {seed} | {'true' if factor is None else f'x{factor:g}'} | "
                      f"{row['registered']}/{row['views']} | {row['rotation_deg']:.4f} | {row['centre_spread']:.3g} | "
                      f"{kinds} | {row['focal_px']:.1f} ({row['true_focal_px']:.0f}) | {row['seconds']:.1f} |")
        ratios_a, counts_a = np.array(ratios), np.array(counts)
        over = threshold_counts(ratios_a, counts_a)
        print(f"\n{points} points: {len(ratios_a)} pure-rotation edges, {int(counts_a.min())}-{int(counts_a.max())} "
              f"matches, largest ρ {ratios_a.max():.2f}; edges at or above the threshold: "
              + ", ".join(f"{k}: {n}" for k, n in over.items()) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
