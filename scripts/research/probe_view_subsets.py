#!/usr/bin/env python
"""Probe: does rotonly hold on view graphs it was not tuned on? `rotonly run` (in-process) on
random subsets of a Strecha input's views, scored against the ground truth.

A subset keeps the chosen views, their keypoints and the pairs among them, nothing else: the
view graphs get sparser, with leaves and wide-baseline pairs, as a user's smaller or patchier
capture would. One table row per run (views, registered, with a centre, mean rotation and
position error), then a summary: median and mean errors, runs whose positions collapsed
(position error > ``--collapse`` GT units) and runs whose rotations failed (> 1 deg).

    python scripts/research/probe_view_subsets.py --root DATA/strecha --scene castle-P19 --input database \
        --views 8 --trials 10
"""

from __future__ import annotations

import argparse
import copy
import logging
import sys

import numpy as np


def view_subset(scene, keep: set[int]):
    """``scene`` (an SfMScene as read) with the views of ``keep`` and the pairs among them only."""
    subset = copy.deepcopy(scene)
    subset.views = {v: view for v, view in subset.views.items() if v in keep}
    subset.keypoints = {v: kp for v, kp in subset.keypoints.items() if v in keep}
    subset.normalized = {v: xy for v, xy in subset.normalized.items() if v in keep}
    subset.pairs = {key: pair for key, pair in subset.pairs.items() if key[0] in keep and key[1] in keep}
    return subset


def subset_row(result) -> dict:
    """What one run of a subset gives: registered views, views with a centre, mean errors."""
    evaluation = result.evaluation or {}
    position = evaluation.get("position_error") or {}
    return {"registered": len(result.rotations),
            "centres": int(sum(np.isfinite(c).all() for c in result.centers.values())),
            "rotation_deg": float(evaluation["rotation_error_deg"]["mean"]),
            "position": float(position.get("mean", np.nan))}


def main(argv: list[str] | None = None) -> int:
    import rotonly_cli
    from rotonly_cli.errors import AlgorithmError
    from rotonly_cli.stages.load import read_input

    from strecha_gt import add_scene_arguments, scene_input

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scene_arguments(parser, "castle-P19")
    parser.add_argument("--views", type=int, default=8, help="views per subset")
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--seed", type=int, default=7, help="seed of the subsets (the runs use rotonly's own)")
    parser.add_argument("--collapse", type=float, default=0.5, help="position error (GT units) counted as collapsed")
    args = parser.parse_args(argv)
    input_path, _ = scene_input(parser, args)
    scene, _ = read_input(input_path)
    view_ids = sorted(scene.views)
    if not 2 <= args.views <= len(view_ids):
        parser.error(f"--views: between 2 and {len(view_ids)}")
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    rng = np.random.default_rng(args.seed)
    print(f"## {args.trials} subsets of {args.views} views of {args.scene} ({args.input})\n")
    print("| views | registered | with a centre | rotation (deg) | position (GT units) |")
    print("|---|---|---|---|---|")
    rows = []
    for _ in range(args.trials):
        keep = {int(v) for v in rng.choice(view_ids, args.views, replace=False)}
        try:
            row = subset_row(rotonly_cli.run(view_subset(scene, keep), gt=args.root / args.scene, progress=False))
        except AlgorithmError as exc:  # no reconstruction: counted, not fatal
            row = {"registered": 0, "centres": 0, "rotation_deg": np.nan, "position": np.nan, "error": str(exc)}
        rows.append(row)
        print(f"| {' '.join(map(str, sorted(keep)))} | {row['registered']} | {row['centres']} | "
              f"{row['rotation_deg']:.4f} | {row['position']:.4f} |", flush=True)
    rotation = np.array([row["rotation_deg"] for row in rows])
    position = np.array([row["position"] for row in rows])
    print(f"\nruns {len(rows)}, without a reconstruction {int(np.isnan(rotation).sum())}; rotation median "
          f"{np.nanmedian(rotation):.4f}, mean {np.nanmean(rotation):.4f} deg; position median "
          f"{np.nanmedian(position):.4f}; collapsed (> {args.collapse:g}) {int((position > args.collapse).sum())}; "
          f"rotation > 1 deg {int((rotation > 1.0).sum())}; registered {sum(row['registered'] for row in rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
