#!/usr/bin/env python
"""Probe: does rotonly hold on low-resolution images (thumbnails, video frames, old cameras)?
Each scene's images are shrunk by ``--factors`` (OpenCV's area average), described and matched
again with pycolmap's CPU SIFT (one PINHOLE camera with the ground-truth K scaled to the new
size, exhaustive matching, COLMAP's default verification), and run through `rotonly run`
in-process. Beside it, on the same database: rotonly's averaged rotations (GRRM's start,
``--no-grrm``), pycolmap's bundle adjustment (intrinsics held) started from rotonly's model,
and with ``--mapper`` pycolmap's global mapper (intrinsics held). Fewer pixels mean fewer
matches per pair and larger angular keypoint noise: what the noisier-keypoint probe adds as
noise, this one gets from real detections.

    python scripts/research/probe_low_resolution.py --root DATA/strecha --factors 2 3 4 \
        [--scenes castle-P19 ...] [--mapper] [--work DIR]

``--work`` keeps the shrunk images and databases (reused when present); default: a
temporary folder.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def scaled_camera(params: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """PINHOLE (fx, fy, cx, cy) in COLMAP's pixel convention (the image's corner at 0) for the
    image resized from ``size`` to ``new_size`` (width, height): every parameter scales with
    its axis."""
    sx, sy = new_size[0] / size[0], new_size[1] / size[1]
    fx, fy, cx, cy = np.asarray(params, dtype=float)
    return np.array([fx * sx, fy * sy, cx * sx, cy * sy])


def shrunk_images(images: Path, out: Path, factor: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """Every ``*.jpg`` of ``images`` shrunk by ``factor`` (area average, JPEG quality 92) into
    ``out``; returns the (width, height) before and after (of the first image)."""
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    sizes = None
    for path in sorted(images.glob("*.jpg")):
        image = cv2.imread(str(path))
        height, width = image.shape[:2]
        new_size = (width // factor, height // factor)
        if factor != 1:
            image = cv2.resize(image, new_size, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / path.name), image, [cv2.IMWRITE_JPEG_QUALITY, 92])
        sizes = sizes or ((width, height), new_size)
    if sizes is None:
        raise FileNotFoundError(f"no .jpg images in {images}")
    return sizes


def matched_database(images: Path, database: Path, camera: np.ndarray, threads: int) -> Path:
    """pycolmap's CPU SIFT and exhaustive matching of ``images`` into ``database``, all images
    on one PINHOLE ``camera`` (fx, fy, cx, cy), as `colmap feature_extractor` with
    ``--ImageReader.single_camera 1 --ImageReader.camera_params`` and `colmap exhaustive_matcher`
    make it. An existing database is kept."""
    import pycolmap

    if database.is_file():
        return database
    partial = database.with_suffix(".partial.db")
    partial.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=",".join(f"{p:.6f}" for p in camera))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        pycolmap.extract_features(partial, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(partial, device=pycolmap.Device.cpu)
    finally:
        pycolmap.logging.minloglevel = previous
    partial.rename(database)
    return database


def main(argv: list[str] | None = None) -> int:
    from probe_keypoint_noise import bundle_adjusted_rotation_error, mapper_rotation_error
    from probe_view_subsets import subset_row

    import rotonly_cli
    from rotonly_cli.io.colmap import read_database
    from rotonly_cli.io.strecha import read_strecha_dir
    from rotonly_cli.runtime.parallel import usable_cpus

    from strecha_gt import add_scenes_arguments

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_scenes_arguments(parser)
    parser.add_argument("--factors", type=int, nargs="+", default=[2, 3, 4],
                        help="shrink factors of the scenes' images (1: as they are)")
    parser.add_argument("--mapper", action="store_true",
                        help="pycolmap's global mapper (intrinsics held) on the same databases")
    parser.add_argument("--work", type=Path, default=None,
                        help="keep the shrunk images and databases here (reused when present)")
    args = parser.parse_args(argv)
    if any(factor < 1 for factor in args.factors):
        parser.error("--factors: whole numbers >= 1")
    logging.getLogger("rotonly_cli").setLevel(logging.ERROR)
    threads = usable_cpus()
    mapper_header = " global mapper (deg, registered) |" if args.mapper else ""
    print("| scene | factor | image size | verified matches | registered | rotation (deg) | averaged start (deg) "
          f"| position (GT units) | BA from rotonly's model (deg) |{mapper_header} time (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|" + ("---|" if args.mapper else ""))
    with tempfile.TemporaryDirectory(prefix="rotonly-probe-lowres-") as scratch:
        work = args.work or Path(scratch)
        for name in args.scenes:
            scene_dir = args.root / name
            if not (scene_dir / "images").is_dir() or not (scene_dir / "gt_dense_cameras").is_dir():
                parser.error(f"--root/--scenes: {scene_dir} needs images/ and gt_dense_cameras/")
            gt_path = scene_dir / "gt_dense_cameras"
            gt = read_strecha_dir(scene_dir)
            camera = np.median(np.stack([k.params for k in gt.intrinsics.values()]), axis=0)
            for factor in args.factors:
                folder = work / f"{name}_x{factor}"
                size, new_size = shrunk_images(scene_dir / "images", folder / "images", factor)
                database = matched_database(folder / "images", folder / "database.db",
                                            scaled_camera(camera, size, new_size), threads)
                matched = read_database(database)
                matches = sum(len(pair.matches) for pair in matched.pairs.values())
                started = time.perf_counter()
                result = rotonly_cli.run(database, gt=gt_path, jobs=threads, progress=False)
                seconds = time.perf_counter() - started
                row = subset_row(result)
                averaged = subset_row(rotonly_cli.run(database, gt=gt_path, jobs=threads, grrm=False,
                                                      progress=False))
                mapper = ""
                if args.mapper:
                    mapped_error, mapped = mapper_rotation_error(database, matched, gt_path, threads)
                    mapper = f" {mapped_error:.4f} ({mapped} / {len(gt.views)}) |"
                print(f"| {name} | {factor} | {new_size[0]} x {new_size[1]} | {matches} | {row['registered']} / "
                      f"{len(gt.views)} | {row['rotation_deg']:.4f} | {averaged['rotation_deg']:.4f} "
                      f"| {row['position']:.4f} | {bundle_adjusted_rotation_error(result, gt_path):.4f} |{mapper} "
                      f"{seconds:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
