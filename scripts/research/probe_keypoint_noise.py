#!/usr/bin/env python
"""Probe: does rotonly hold when the keypoints are noisier than Strecha's (~0.2 px)? Coarser
detectors, downsampled or blurred images give 0.5-1 px. Each Strecha database is written
again with every keypoint moved by seeded Gaussian noise of ``--noise-px`` (per coordinate;
the matches and the camera stay), `rotonly run` in-process, and as a reference pycolmap's
bundle adjustment (intrinsics held) started from rotonly's own model: what the same matches
and tracks give when every pose and point is free. With ``--mapper`` also pycolmap's global
mapper (GLOMAP, intrinsics held, as rotonly holds a known camera) on the same noisy database:
what a user's other tool gives on the same input. One row per scene and noise level:
registered views, rotation and position errors, and the run's wall time.

    python scripts/research/probe_keypoint_noise.py --root DATA/strecha --noise-px 0.5 1.0 \
        [--scenes castle-P19 ...] [--seed 0] [--mapper]
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


def noisy_database(scene, noise_px: float, out: Path, seed: int = 0) -> Path:
    """``scene`` (a database as read) written to ``out`` with every keypoint moved by
    N(0, ``noise_px``) per coordinate (seeded, views in the order read)."""
    from rotonly_cli.io.colmap import write_database

    rng = np.random.default_rng(seed)
    keypoints = {v: k + rng.normal(scale=noise_px, size=k.shape) for v, k in scene.keypoints.items()}
    write_database(out, replace(scene, keypoints=keypoints))
    return out


def bundle_adjusted_rotation_error(result, gt_path: Path) -> float:
    """Mean rotation error (deg) of pycolmap's bundle adjustment, intrinsics held, started from
    ``result`` (a rotonly run): every pose and point free."""
    import pycolmap

    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.io.detect import read_scene

    reconstruction = result.to_pycolmap()
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.print_summary = False  # (pycolmap 4.2 still writes two glog lines per call to stderr)
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        pycolmap.bundle_adjustment(reconstruction, options)
    finally:
        pycolmap.logging.minloglevel = previous
    with tempfile.TemporaryDirectory(prefix="rotonly-probe-ba-") as folder:
        reconstruction.write(folder)
        return float(evaluate(read_scene(gt_path), read_scene(Path(folder))).rotation_error_deg.mean)


def mapper_rotation_error(database: Path, scene, gt_path: Path, threads: int) -> tuple[float, int]:
    """(mean rotation error (deg) after rotation-only alignment, views registered) of pycolmap's
    global mapper on ``database`` (``scene``: the database as read), intrinsics held."""
    from rotonly_cli.baselines.references import pycolmap_global_mapper
    from rotonly_cli.bench.paper_multiview import aligned_errors
    from rotonly_cli.io.detect import read_ground_truth

    from strecha_gt import gt_poses_for

    view_ids = sorted(scene.views)
    R_gt, _ = gt_poses_for(read_ground_truth(gt_path), scene, view_ids)
    mapped = pycolmap_global_mapper(database, seed=0, num_threads=threads)
    names = [scene.views[v].name for v in view_ids]
    R_map = np.stack([mapped.get(name, np.full((3, 3), np.nan)) for name in names])
    return float(np.nanmean(aligned_errors(R_map, R_gt))), sum(name in mapped for name in names)


def main(argv: list[str] | None = None) -> int:
    from probe_view_subsets import subset_row

    import rotonly_cli
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.runtime.parallel import usable_cpus

    from strecha_gt import add_scenes_arguments, scene_database

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scenes_arguments(parser)
    parser.add_argument("--noise-px", type=float, nargs="+", default=[0.0, 0.5, 1.0],
                        help="keypoint noise added (px per coordinate; 0: the database as it is)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise (the runs use rotonly's own)")
    parser.add_argument("--mapper", action="store_true",
                        help="pycolmap's global mapper (intrinsics held) on the same databases")
    args = parser.parse_args(argv)
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    mapper_header = " global mapper (deg, registered) |" if args.mapper else ""
    print("| scene | noise added (px) | registered | rotation (deg) | position (GT units) "
          f"| BA from rotonly's model (deg) |{mapper_header} time (s) |")
    print("|---|---|---|---|---|---|---|" + ("---|" if args.mapper else ""))
    with tempfile.TemporaryDirectory(prefix="rotonly-probe-") as scratch:
        for name in args.scenes:
            database, gt = scene_database(parser, args.root, name)
            scene = read_database(database)
            for noise in args.noise_px:
                path = database if noise == 0 else noisy_database(scene, noise, Path(scratch) / f"{name}_{noise}.db",
                                                                  args.seed)
                started = time.perf_counter()
                result = rotonly_cli.run(path, gt=gt, jobs=usable_cpus(), progress=False)
                seconds = time.perf_counter() - started
                row = subset_row(result)
                mapper = ""
                if args.mapper:
                    mapped_error, mapped = mapper_rotation_error(path, scene, gt, usable_cpus())
                    mapper = f" {mapped_error:.4f} ({mapped} / {len(scene.views)}) |"
                print(f"| {name} | {noise:g} | {row['registered']} / {len(scene.views)} | {row['rotation_deg']:.4f} "
                      f"| {row['position']:.4f} | {bundle_adjusted_rotation_error(result, gt):.4f} |{mapper} "
                      f"{seconds:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
