#!/usr/bin/env python
"""Probe: does rotonly see images taken at another zoom under one camera? A zoom lens under
COLMAP's ``--ImageReader.single_camera 1`` (or OpenMVG's ``-k``, or two devices under one
camera) gives images of two focal lengths one camera. Each Strecha database is written again
with every ``--every``-th image (the 2nd, 5th, 8th, ... in image-id order) taken at ``--zooms``
x the focal: its keypoints scaled about the principal point, exactly a focal change for a
pinhole camera; the camera, still marked known, stays one. `rotonly run` in-process with the
zoom check (`IntrinsicsOptions.zoom_check`) and without it; one row per scene and zoom:
rotation error, cameras written, the zoomed images the check found, and whether it warned
(docs/algorithms.md §8 "Images at another zoom").

    python scripts/research/probe_zoom.py --root DATA/strecha [--scenes Herz-Jesus-P8 ...] \
        [--zooms 1.03 1.05 1.15] [--every 3]
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np


def zoomed_views(scene, every: int) -> list[int]:
    """Every ``every``-th view of ``scene`` in id order, from the second."""
    return [view_id for n, view_id in enumerate(sorted(scene.views)) if n % every == 1]


def zoomed_database(scene, views: list[int], zoom: float, out: Path) -> Path:
    """``scene`` (a database as read, one camera) written to ``out`` with the keypoints of
    ``views`` scaled by ``zoom`` about the camera's principal point (COLMAP's convention)."""
    from rotonly_cli.io import cameras
    from rotonly_cli.io.colmap import write_database

    (camera,) = scene.intrinsics.values()
    principal_point = np.asarray(camera.params, dtype=np.float64)[cameras.parameter_groups(camera)["principal_point"]]
    keypoints = {v: principal_point + zoom * (k - principal_point) if v in views else k
                 for v, k in scene.keypoints.items()}
    write_database(out, replace(scene, keypoints=keypoints))
    return out


def found_views(result) -> list[int]:
    """The views the zoom check gave a camera of their own (or named, for twins)."""
    check = result.reports.get("intrinsics", {}).get("zoom_check") or {}
    groups = [finding["groups"] for finding in check.get("disagree", [])]
    return sorted(v for pair in groups for v in min(pair, key=lambda group: len(group["views"]))["views"])


def image_stems(scene, view_ids: list[int]) -> str:
    """The image names of ``view_ids`` without extension ("–" for none)."""
    return " ".join(Path(scene.views[v].name).stem for v in view_ids) or "–"


def main(argv: list[str] | None = None) -> int:
    import rotonly_cli
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.options import IntrinsicsOptions, RunOptions
    from rotonly_cli.runtime.parallel import usable_cpus

    from strecha_gt import add_scenes_arguments, scene_database

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scenes_arguments(parser)
    parser.add_argument("--zooms", type=float, nargs="+", default=[1.03, 1.05, 1.15],
                        help="focal factor of the zoomed images")
    parser.add_argument("--every", type=int, default=3, help="every this many images is zoomed (from the second)")
    args = parser.parse_args(argv)
    if args.every < 2:
        parser.error("--every must be at least 2 (some images stay unzoomed)")
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    print("| scene | zoom | zoomed images | rotation (deg), zoom check | cameras written | images found "
          "| warned | rotation (deg), no check |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="rotonly-probe-zoom-") as scratch:
        for name in args.scenes:
            database, gt = scene_database(parser, args.root, name)
            scene = read_database(database)
            if len(scene.intrinsics) != 1:
                parser.error(f"{database}: {len(scene.intrinsics)} cameras; the probe zooms under one")
            views = zoomed_views(scene, args.every)
            for zoom in args.zooms:
                path = zoomed_database(scene, views, zoom, Path(scratch) / f"{name}_{zoom}.db")
                runs = {}
                for check in (True, False):
                    options = RunOptions(jobs=usable_cpus(), intrinsics=IntrinsicsOptions(zoom_check=check))
                    runs[check] = rotonly_cli.run(path, gt=gt, options=options, progress=False)
                with_check = runs[True]
                warned = any("disagree on the focal" in w for w in with_check.summary.get("warnings", []))
                print(f"| {name} | {zoom:g} | {image_stems(scene, views)} "
                      f"| {with_check.evaluation['rotation_error_deg']['mean']:.4f} "
                      f"| {len(with_check.scene.intrinsics)} | {image_stems(scene, found_views(with_check))} "
                      f"| {'yes' if warned else 'no'} | {runs[False].evaluation['rotation_error_deg']['mean']:.4f} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
