#!/usr/bin/env python
"""Probe: does rotonly hold on sequentially matched captures? `rotonly run` (in-process) on
each Strecha input with only the pairs a sequential matcher would have made: images at most
``--window`` apart in file-name order (COLMAP's ``sequential_matcher``, OpenMVG's
``PairGenerator`` with a contiguous window; video and drone strips are matched this way).

The view graph becomes a band: every view still connected, but the parts of the capture are
tied together by the tracks of a few neighbouring pairs only, which is where LiGT's scale
must pass. One table row per scene, input and window: views registered, views with a
centre, mean rotation and position error against the GT.

    python scripts/research/probe_sequential.py --root DATA/strecha --windows 1 2 3 \
        [--scenes castle-P19 ...] [--inputs database openmvg]
"""

from __future__ import annotations

import argparse
import copy
import logging
import sys
from pathlib import Path

import numpy as np


def sequential_pairs(scene, window: int):
    """``scene`` (an SfMScene as read) with the pairs of views at most ``window`` apart in
    image-name order only."""
    order = {v: rank for rank, v in enumerate(sorted(scene.views, key=lambda v: Path(scene.views[v].name).name))}
    banded = copy.copy(scene)
    banded.pairs = {key: pair for key, pair in scene.pairs.items() if abs(order[key[0]] - order[key[1]]) <= window}
    return banded


def main(argv: list[str] | None = None) -> int:
    from probe_view_subsets import subset_row

    import rotonly_cli
    from rotonly_cli.errors import AlgorithmError
    from rotonly_cli.stages.load import read_input

    from strecha_gt import add_scenes_arguments

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scenes_arguments(parser)
    parser.add_argument("--inputs", nargs="+", choices=("database", "openmvg"), default=["database", "openmvg"])
    parser.add_argument("--windows", nargs="+", type=int, default=[1, 2, 3])
    args = parser.parse_args(argv)
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    print("| scene | input | window | pairs | registered | with a centre | rotation (deg) | position (GT units) |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.scenes:
        for kind in args.inputs:
            path = args.root / name / ("database.db" if kind == "database" else "openmvg/sfm_data.json")
            if not path.is_file():
                parser.error(f"--root/--scenes: no {path}")
            scene, _ = read_input(path)
            for window in args.windows:
                banded = sequential_pairs(scene, window)
                try:
                    row = subset_row(rotonly_cli.run(banded, gt=args.root / name, progress=False))
                except AlgorithmError as exc:  # no reconstruction: a row, not fatal
                    row = {"registered": 0, "centres": 0, "rotation_deg": np.nan, "position": np.nan,
                           "error": str(exc)}
                print(f"| {name} | {kind} | {window} | {len(banded.pairs)} | {row['registered']} / {len(scene.views)} "
                      f"| {row['centres']} | {row['rotation_deg']:.4f} | {row['position']:.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
