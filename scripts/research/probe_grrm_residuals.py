#!/usr/bin/env python
"""Probe: which property of a scene's keypoint errors drives GRRM's rotation error.

Runs rotonly's chain in-process on one Strecha scene (database or OpenMVG input) up to its
triangulated tracks, keeps only the matches inside those tracks, and re-runs identification,
TRRM, the L1-IRLS average and GRRM (from the loaded relative poses) on keypoints rebuilt
around the ground truth:

* ``real``: the input keypoints themselves;
* ``iid``: GT projections of the tracks (triangulated with the GT cameras) plus isotropic
  Gaussian noise whose RMS equals the real keypoints' residual RMS;
* ``shuffled all / within image / within track``: GT projections plus the real residuals,
  permuted over all observations, among the observations of each image, or among those of
  each track. The distribution of the errors is kept; only where each error sits changes.

Prints the mean rotation error (deg, geodesic after the best global rotation) of the
L1-IRLS start and of GRRM for every row, and GRRM's per-camera errors. A large gap between
``real`` and the shuffled rows says that the error comes from where the residuals sit in the
images, not from their size. README "Known limits" uses this to explain Herz-Jesus-P8 from
OpenMVG's matches, and GRRM against its start on fountain-P11.

    python scripts/research/probe_grrm_residuals.py --root DATA/strecha --scene Herz-Jesus-P8 --input openmvg
"""

from __future__ import annotations

import argparse
import copy
import sys
from dataclasses import replace

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from strecha_gt import add_scene_arguments, gt_poses_for, gt_track_residuals, scene_input

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)  # the stages log at INFO; this prints a table

    from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
    from rotonly_cli.pipeline import STAGE_FUNCTIONS, Run, RunOptions, load_stage
    from rotonly_cli.scene.view_graph import view_index
    from rotonly_cli.stages.load import focal_length


    input_path, gt = scene_input(parser, args)

    options = RunOptions(progress=False)
    run = load_stage(input_path, options)
    loaded = copy.deepcopy(run.graph)  # relative poses and matches as loaded
    for stage in ("identify", "refine", "average", "optimize", "translate", "triangulate"):
        STAGE_FUNCTIONS[stage](run)
    graph, scene = run.graph, run.scene
    index = view_index(graph)
    view_ids = graph.view_ids()
    R_gt, C_gt = gt_poses_for(gt, scene, view_ids)

    def errors_deg(R: np.ndarray) -> np.ndarray:
        return rotation_errors_after_alignment(R, R_gt)[0]

    # observations of rotonly's tracks, grouped by point, and their GT reprojections
    tracks = gt_track_residuals(run.structure, view_ids, scene.normalized, R_gt, C_gt)
    obs_point, obs_view, obs_kp = tracks["point"], tracks["view_row"], tracks["keypoint"]
    obs_xy, clean = tracks["observed"], tracks["projected"]
    in_view = [np.flatnonzero(obs_view == r) for r in range(len(view_ids))]
    # point of every keypoint (-1: in no track); keep the matches inside one track
    point_of = [np.full(len(scene.normalized[v]), -1) for v in view_ids]
    for r, rows in enumerate(in_view):
        point_of[r][obs_kp[rows]] = obs_point[rows]
    for edge in loaded.edges:
        if edge.active:
            a = point_of[index[edge.i]][edge.matches[:, 0]]
            b = point_of[index[edge.j]][edge.matches[:, 1]]
            edge.matches = edge.matches[(a == b) & (a >= 0)]
            if edge.num_inliers < options.load.min_inliers:  # e.g. a wrong-model pair's few matches
                edge.filter("too few matches inside the tracks")

    focal = np.array([focal_length(scene.intrinsics[scene.views[v].intrinsics_id]) for v in view_ids])[obs_view]
    residual = obs_xy - clean  # normalized units
    rms_px = float(np.sqrt(((residual * focal[:, None]) ** 2).sum(1).mean()))

    rng = np.random.default_rng(args.seed)

    def permuted_within(groups: np.ndarray) -> np.ndarray:
        order = np.argsort(groups, kind="stable")
        cuts = np.flatnonzero(np.diff(groups[order])) + 1
        out = np.empty_like(order)
        for part in np.split(order, cuts):
            out[part] = rng.permutation(part)
        return out

    variants = {
        "real keypoints": obs_xy,
        f"GT projections + iid noise ({rms_px:.3f} px RMS)":
            clean + rng.normal(size=clean.shape) * (rms_px / np.sqrt(2)) / focal[:, None],
        "GT projections + real residuals shuffled over all": clean + residual[rng.permutation(len(residual))],
        "... shuffled within each image": clean + residual[permuted_within(obs_view)],
        "... shuffled within each track": clean + residual[permuted_within(obs_point)],
    }
    kept = sum(e.num_inliers for e in loaded.edges if e.active)
    print(f"{args.scene}, {args.input} input: {len(run.structure.observations)} tracks, {len(obs_xy)} observations, "
          f"{kept} matches inside tracks; GT residual RMS {rms_px:.3f} px; rotonly run: "
          f"{errors_deg(run.rotations).mean():.4f} deg")
    print("| keypoints | L1-IRLS start (deg) | GRRM (deg) | GRRM per camera (deg) |")
    print("|---|---|---|---|")
    for label, xy in variants.items():
        normalized = {v: x.copy() for v, x in scene.normalized.items()}
        for r, rows in enumerate(in_view):
            normalized[view_ids[r]][obs_kp[rows]] = xy[rows]
        rebuilt = Run(str(input_path), run.input_kind, replace(scene, normalized=normalized), copy.deepcopy(loaded),
                      options)
        for stage in ("identify", "refine", "average"):
            STAGE_FUNCTIONS[stage](rebuilt)
        start = errors_deg(rebuilt.rotations).mean()
        STAGE_FUNCTIONS["optimize"](rebuilt)
        errors = errors_deg(rebuilt.rotations)
        print(f"| {label} | {start:.4f} | {errors.mean():.4f} | {' '.join(f'{e:.3f}' for e in errors)} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
