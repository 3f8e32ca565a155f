#!/usr/bin/env python
"""Probe: could the pairs the load stage drops for too few inliers (``--min-inliers``) serve as
evidence for the tracks (issue "weak pairs as evidence")?

Runs ``rotonly run`` in-process on a Strecha input and, for every pair filtered for too few
inliers, compares its input matches with the run's global poses and with the ground truth:
how many lie within ``--threshold-px`` (Sampson distance) of the epipolar geometry the global
poses give the pair, and how many of those also lie within it under the GT poses (a match the
global poses confirm but the GT refutes is a wrong match along its epipolar line). Prints one
table row per input: what weak pairs could add to the tracks at most.

    python scripts/research/probe_weak_pairs.py --root DATA/strecha --scene castle-P19 --input database
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def weak_pair_agreement(result, scene, gt_R: dict, gt_C: dict, threshold_px: float) -> dict:
    """Counts over the pairs of ``result.graph`` filtered for too few inliers whose two views
    have global poses: pairs, matches, matches within ``threshold_px`` of the global epipolar
    geometry, and of those the ones within it under the GT poses (``gt_R``/``gt_C`` by view id)."""
    from rotonly_cli.geometry import pairwise as pg

    counts = {"pairs": 0, "matches": 0, "global": 0, "global_and_gt": 0}

    def sampson_px(R_i, C_i, R_j, C_j, x_i, x_j, focal):
        t = R_j @ (C_i - C_j)
        return pg.sampson_errors(R_j @ R_i.T, t / np.linalg.norm(t), x_i, x_j) * focal

    for edge in result.graph.edges:
        if edge.status == "active" or "few inliers" not in edge.reason:
            continue
        if edge.i not in result.rotations or edge.j not in result.rotations:
            continue
        matches = np.asarray(scene.pairs[(edge.i, edge.j)].matches, dtype=np.int64).reshape(-1, 2)
        x_i, x_j = scene.normalized[edge.i][matches[:, 0]], scene.normalized[edge.j][matches[:, 1]]
        focal = 0.5 * (scene.intrinsics[scene.views[edge.i].intrinsics_id].focal_px
                       + scene.intrinsics[scene.views[edge.j].intrinsics_id].focal_px)
        near_global = sampson_px(result.rotations[edge.i], result.centers[edge.i], result.rotations[edge.j],
                                 result.centers[edge.j], x_i, x_j, focal) <= threshold_px
        near_gt = sampson_px(gt_R[edge.i], gt_C[edge.i], gt_R[edge.j], gt_C[edge.j], x_i, x_j, focal) <= threshold_px
        counts["pairs"] += 1
        counts["matches"] += len(matches)
        counts["global"] += int(near_global.sum())
        counts["global_and_gt"] += int((near_global & near_gt).sum())
    return counts


def main(argv: list[str] | None = None) -> int:
    import rotonly_cli
    from rotonly_cli.stages.load import read_input

    from strecha_gt import add_scene_arguments, gt_poses_for, scene_input

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser, "castle-P19")
    parser.add_argument("--threshold-px", type=float, default=1.0)
    parser.add_argument("--min-inliers", type=int, default=None, help="rotonly run's --min-inliers")
    args = parser.parse_args(argv)
    input_path, gt = scene_input(parser, args)
    result = rotonly_cli.run(input_path, progress=False, min_inliers=args.min_inliers)
    scene, _ = read_input(input_path)
    view_ids = sorted(result.rotations)
    R_gt, C_gt = gt_poses_for(gt, scene, view_ids)
    counts = weak_pair_agreement(result, scene, dict(zip(view_ids, R_gt)), dict(zip(view_ids, C_gt)),
                                 args.threshold_px)
    used = sum(edge.num_inliers for edge in result.graph.edges if edge.status == "active")
    print(f"## weak pairs of {args.scene} ({args.input}), within {args.threshold_px:g} px\n")
    print("| weak pairs | their matches | near the global geometry | ... and the GT's | matches in active edges |")
    print("|---|---|---|---|---|")
    print(f"| {counts['pairs']} | {counts['matches']} | {counts['global']} | {counts['global_and_gt']} | {used} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
