"""GRRM's rotations against its own start (the L1-IRLS average of the TRRM pairs), from a
finished `rotonly run` workspace: the error of each against the ground truth, and GT-free
scores that could tell them apart (the pairs' own TRRM costs at the global rotations).

    python scripts/research/probe_grrm_vs_average.py --out OUT --input DATABASE_OR_SFM_DATA \
        --gt GT/sfm_data.json [--matches-dir DIR]

``--smooth-views K`` also splits each view's error (the rotation vector of R_est Sᵀ R_gtᵀ, views
in id order: capture order for `rotonly simulate multiview`) into its moving average over K
neighbouring views (the smooth bend along the path) and the rest.

OUT/state.npz holds the pairs as the run ended (their TRRM-refined relative rotations and
inlier matches, the reject stage's drops applied) and the final rotations (GRRM's, after the
reject stage's re-solves). The average here is averaging.average_rotations on those pairs (the
average stage's outlier-edge filter left out). Research only (ground truth scores the result).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
from rotonly_cli.geometry.averaging import average_rotations
from rotonly_cli.io import detect
from rotonly_cli.stages.load import read_input

#: matches per chunk of the per-edge costs
CHUNK_MATCHES = 1 << 21


def _gt_rotations(gt_path: Path, names: list[str]) -> np.ndarray:
    gt = detect.read_scene(gt_path)
    by_name = {view.name: gt.poses[k].R_cam_from_world for k, view in gt.views.items() if k in gt.poses}
    return np.stack([by_name[name] for name in names])


def edge_costs(R_cam_from_world: np.ndarray, edge_rows: np.ndarray, offsets: np.ndarray, matches: np.ndarray,
               edge_ids: np.ndarray, normalized: dict) -> np.ndarray:
    """(E, 2): each pair's TRRM cost (sum of squared bearing residuals, both views, eq:ROMresBearing)
    and its median squared residual, at the relative rotation of the global ones."""
    out = np.empty((len(edge_rows), 2))
    start = 0
    while start < len(edge_rows):
        stop = start
        while stop < len(edge_rows) and offsets[stop + 1] - offsets[start] <= CHUNK_MATCHES or stop == start:
            stop += 1
        rows = edge_rows[start:stop]
        R_ij = R_cam_from_world[rows[:, 1]] @ np.swapaxes(R_cam_from_world[rows[:, 0]], 1, 2)
        x_i = np.concatenate([normalized[int(i)][matches[offsets[e]:offsets[e + 1], 0]]
                              for e, i in zip(range(start, stop), edge_ids[start:stop, 0])])
        x_j = np.concatenate([normalized[int(j)][matches[offsets[e]:offsets[e + 1], 1]]
                              for e, j in zip(range(start, stop), edge_ids[start:stop, 1])])
        batch = pg.pack_flat(x_i, x_j, offsets[start:stop + 1] - offsets[start])
        r = pg.trrm_residuals(R_ij, batch).residuals
        sq = (r.reshape(len(x_i), -1) ** 2).sum(axis=1)
        out[start:stop, 0] = batch.segment_sum(sq)
        out[start:stop, 1] = [np.median(sq[a:b]) for a, b in zip(batch.offsets[:-1], batch.offsets[1:])]
        start = stop
    return out


def smooth_and_rough(R_aligned: np.ndarray, R_gt: np.ndarray, width: int) -> tuple[float, float]:
    """Mean angle (deg) of the moving average over ``width`` consecutive views of the error
    rotation vectors log(R_aligned R_gtᵀ), and of what is left of them (ends padded by their
    last value)."""
    from scipy.ndimage import uniform_filter1d

    from rotonly_cli.geometry import so3

    v = so3.log(R_aligned @ np.swapaxes(R_gt, 1, 2))
    smooth = uniform_filter1d(v, width, axis=0, mode="nearest")
    return (float(np.degrees(np.linalg.norm(smooth, axis=1)).mean()),
            float(np.degrees(np.linalg.norm(v - smooth, axis=1)).mean()))


@dataclass
class Workspace:
    """What a finished run's workspace holds of GRRM's problem: its views (ids, names, in the
    rotation rows' order), the active REGULAR pairs as view ids and rows, their matches (one
    table, ``offsets`` per pair), the L1-IRLS average of the pairs, the final rotations, the
    ground truth and the input scene (its normalized keypoints)."""

    ids: list
    names: list
    edge_ids: np.ndarray
    edge_rows: np.ndarray
    matches: np.ndarray
    offsets: np.ndarray
    averaged: np.ndarray
    final: np.ndarray
    R_gt: np.ndarray
    scene: object


def load_workspace(out: Path, input_path: Path, gt: Path, matches_dir: Path | None = None) -> Workspace:
    """The :class:`Workspace` of ``out`` (a `rotonly run` OUT) on ``input_path`` against ``gt``."""
    state = np.load(out / "state.npz")
    meta = json.loads(str(state["meta_json"]))
    ids = [view[0] for view in meta["views"]]
    names = [view[1] for view in meta["views"]]
    row = {v: r for r, v in enumerate(ids)}
    # the active REGULAR pairs (GRRM's), their matches as offsets into state["matches"]
    kept = np.array([e["status"] == "active" and e["scene_kind"] == "REGULAR" for e in meta["edges"]])
    all_offsets = state["match_offsets"]
    edge_ids = state["edge_views"][kept]
    edge_rows = np.vectorize(row.get)(edge_ids)
    averaged = average_rotations(len(ids), edge_rows[:, 0], edge_rows[:, 1],
                                 state["R_j_from_i"][kept]).R_cam_from_world
    counts = np.diff(all_offsets)[kept]
    # the kept pairs' rows of the match table, in one mask (state[...] reads the whole array each time)
    matches = state["matches"][np.repeat(kept, np.diff(all_offsets))]
    return Workspace(ids, names, edge_ids, edge_rows, matches, np.concatenate([[0], np.cumsum(counts)]), averaged,
                     state["rotations"], _gt_rotations(gt, names), read_input(input_path, matches_dir)[0])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--input", type=Path, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--matches-dir", type=Path, default=None)
    parser.add_argument("--smooth-views", type=int, default=0, help="split the errors at this moving-average width")
    args = parser.parse_args(argv)
    ws = load_workspace(args.out, args.input, args.gt, args.matches_dir)
    edge_ids, edge_rows, matches, offsets, scene = ws.edge_ids, ws.edge_rows, ws.matches, ws.offsets, ws.scene
    averaged, final, R_gt = ws.averaged, ws.final, ws.R_gt
    results = {}
    for name, R in (("average", averaged), ("final (GRRM)", final)):
        errors, S = rotation_errors_after_alignment(R, R_gt)
        if args.smooth_views > 1:
            smooth, rough = smooth_and_rough(R @ S.T, R_gt, args.smooth_views)
            print(f"{name:14s} error along the path: smooth part mean {smooth:.5f} deg, the rest {rough:.5f} deg "
                  f"({args.smooth_views}-view moving average)")
        costs = edge_costs(R, edge_rows, offsets, matches, edge_ids, scene.normalized)
        results[name] = costs
        print(f"{name:14s} rotation error mean {errors.mean():.5f} deg, max {errors.max():.4f}; "
              f"pairs' TRRM cost sum {costs[:, 0].sum():.6g}, sum of median sq {costs[:, 1].sum():.6g}")
    a, f = results["average"], results["final (GRRM)"]
    print(f"pairs where the average costs less: {np.mean(a[:, 0] < f[:, 0]):.3f} (sum), "
          f"{np.mean(a[:, 1] < f[:, 1]):.3f} (median); median ratio average / final "
          f"{np.median(a[:, 0] / f[:, 0]):.5f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
