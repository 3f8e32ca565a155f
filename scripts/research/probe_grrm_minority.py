"""GRRM from the average of a finished run's pairs, with and without the matches on a
minority keypoint of their track (geometry.tracks.minority_keypoint_matches), against GT.

    python scripts/research/probe_grrm_minority.py --out OUT --input DATABASE --gt GT/sfm_data.json

OUT: a `rotonly run` workspace of a version without the filter (its state.npz holds every
match); GRRM runs here in one process. Research only (ground truth scores the result).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from probe_grrm_vs_average import load_workspace

from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
from rotonly_cli.geometry.grrm import GRRMOptions, optimize_global_rotations
from rotonly_cli.geometry.pairwise import ObservedMatches
from rotonly_cli.geometry.tracks import minority_keypoint_matches


def main(argv=None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--input", type=Path, required=True)
    parser.add_argument("--gt", type=Path, required=True)
    parser.add_argument("--matches-dir", type=Path, default=None)
    parser.add_argument("--variants", nargs="+", default=["all", "minority-dropped"])
    args = parser.parse_args(argv)
    ws = load_workspace(args.out, args.input, args.gt, args.matches_dir)
    ids, edge_rows, matches, bounds = ws.ids, ws.edge_rows, ws.matches, ws.offsets
    averaged, R_gt = ws.averaged, ws.R_gt
    scene, counts = ws.scene, np.diff(ws.offsets)
    sizes = np.array([len(scene.normalized[v]) for v in ids])
    offset = np.concatenate([[0], np.cumsum(sizes)])
    edge_of_match = np.repeat(np.arange(len(counts)), counts)
    obs_ids = np.stack([offset[edge_rows[edge_of_match, 0]] + matches[:, 0],
                        offset[edge_rows[edge_of_match, 1]] + matches[:, 1]], axis=1)
    coords = np.concatenate([scene.normalized[v] for v in ids])
    if coords.shape[1] == 2:
        coords = np.hstack([coords, np.ones((len(coords), 1))])
    print(f"average: {rotation_errors_after_alignment(averaged, R_gt)[0].mean():.5f} deg; "
          f"run's final: {rotation_errors_after_alignment(ws.final, R_gt)[0].mean():.5f} deg", flush=True)
    for variant in args.variants:
        t0 = time.perf_counter()
        ob, b = obs_ids, bounds
        if variant == "minority-dropped":
            num_feats = int(matches.max()) + 1
            drop = minority_keypoint_matches(edge_rows[edge_of_match] * num_feats + matches, num_feats)
            keep_counts = np.add.reduceat((~drop).astype(np.int64), bounds[:-1])
            ob = obs_ids[~drop]
            b = np.concatenate([[0], np.cumsum(keep_counts)])
            print(f"  dropped {int(drop.sum())} of {len(drop)} matches ({drop.mean():.3%}); "
                  f"edges below 30 left: {int((keep_counts < 30).sum())}", flush=True)
        res = optimize_global_rotations(averaged, edge_rows, ObservedMatches(coords, ob, b), ob, fixed_view=0,
                                        options=GRRMOptions())
        err = rotation_errors_after_alignment(res.R_cam_from_world, R_gt)[0]
        print(f"{variant:18s} GRRM {err.mean():.5f} deg (max {err.max():.4f}), {res.iterations} it, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
