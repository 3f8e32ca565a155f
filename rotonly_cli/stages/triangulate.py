"""Stage `triangulate`: tracks of all active edges between posed views, triangulated at
once (``geometry.triangulation``), coloured from the images when they can be found."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks
from rotonly_cli.io.types import SfMScene, Structure
from rotonly_cli.io.viewgraph import ViewGraph
from rotonly_cli.stages.translate import graph_tracks

logger = logging.getLogger(__name__)
GREY = 128


def _read_images(paths: list[Path]) -> Iterator[np.ndarray | None]:
    """BGR images in order (None where missing or unreadable), decoded on a thread per
    core: JPEG decoding is most of this stage's time and OpenCV releases the GIL while
    decoding. A generator, so only a few decoded images are alive at once."""
    import cv2
    from concurrent.futures import ThreadPoolExecutor

    def read(path: Path) -> np.ndarray | None:
        return cv2.imread(str(path), cv2.IMREAD_COLOR) if path.is_file() else None

    if len(paths) < 2:
        yield from map(read, paths)
        return
    with ThreadPoolExecutor(max_workers=min(len(paths), os.cpu_count() or 1)) as pool:
        yield from pool.map(read, paths)


def point_colors(scene: SfMScene, image_root: str | Path | None, view_ids: list[int], obs_point: np.ndarray,
                 obs_view_row: np.ndarray, obs_feature: np.ndarray, num_points: int) -> tuple[np.ndarray, dict]:
    """Mean RGB of each point over its observations' pixels (COLMAP pixel convention: the
    pixel holding (u, v) is floor(u), floor(v)); grey where no image could be read."""
    sums = np.zeros((num_points, 3))
    hits = np.zeros(num_points)
    missing: list[str] = []
    if image_root is not None:
        rows = np.unique(obs_view_row).tolist()
        images = _read_images([Path(image_root) / scene.views[view_ids[row]].name for row in rows])
        for row, image in zip(rows, images):
            view = scene.views[view_ids[row]]
            if image is None:
                missing.append(view.name)
                continue
            mask = obs_view_row == row
            pixels = scene.keypoints[view.id][obs_feature[mask]]
            u = np.clip(np.floor(pixels[:, 0]).astype(np.int64), 0, image.shape[1] - 1)
            v = np.clip(np.floor(pixels[:, 1]).astype(np.int64), 0, image.shape[0] - 1)
            rgb = image[v, u, ::-1].astype(float)  # OpenCV is BGR
            # sums of small integers: exact in any order (bincount is ~10x faster than add.at)
            for channel in range(3):
                sums[:, channel] += np.bincount(obs_point[mask], weights=rgb[:, channel], minlength=num_points)
            hits += np.bincount(obs_point[mask], minlength=num_points)
    else:
        missing = ["(no image folder)"]
    colors = np.full((num_points, 3), GREY, dtype=np.uint8)
    seen = hits > 0
    colors[seen] = np.clip(np.round(sums[seen] / hits[seen, None]), 0, 255).astype(np.uint8)
    if image_root is None:
        logger.info("triangulate: no image folder found (give --image-path): point colours are grey")
    elif missing:
        logger.info("triangulate: %d image(s) not found under %s: those colours are grey", len(missing), image_root)
    return colors, {"image_root": None if image_root is None else str(image_root), "images_missing": missing,
                    "points_coloured": int(seen.sum())}


def triangulate_graph(graph: ViewGraph, scene: SfMScene, R_cam_from_world: np.ndarray, centers: np.ndarray,
                      image_root: str | Path | None = None,
                      options: TriangulationOptions | None = None) -> tuple[Structure, dict]:
    """Structure (valid points only, observations as (view id, keypoint)) and report."""
    start = time.perf_counter()
    view_ids = graph.view_ids()
    row_of = {v: r for r, v in enumerate(view_ids)}
    posed = np.all(np.isfinite(R_cam_from_world.reshape(len(view_ids), -1)), axis=1) & \
        np.all(np.isfinite(centers), axis=1)
    edges = [k for k in graph.active_edges()
             if posed[row_of[graph.edges[k].i]] and posed[row_of[graph.edges[k].j]]]
    R = np.where(posed[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, scene.normalized, edges, R)
    C = np.where(posed[:, None], centers, 0.0)
    result = triangulate_tracks(R, C, tracks.track_id, tracks.view, obs_xy, tracks.num_tracks, options)
    valid = result.valid
    kept = tracks.subset(valid)
    points = result.points_in_world[valid]
    colors, color_report = point_colors(scene, image_root, view_ids, kept.track_id, kept.view, kept.feature,
                                        kept.num_tracks)
    obs_view_id = np.asarray(view_ids, dtype=np.int64)[kept.view]
    pairs = list(zip(obs_view_id.tolist(), kept.feature.tolist()))  # one tuple per observation
    offsets = np.asarray(kept.offsets).tolist()
    observations = [pairs[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
    structure = Structure(point_ids=np.arange(kept.num_tracks, dtype=np.int64), points=points, colors=colors,
                          observations=observations)
    error = result.mean_reprojection_error[valid]
    report = {"num_edges": len(edges), "num_tracks": tracks.num_tracks, "num_points": int(valid.sum()),
              "num_rejected": int(tracks.num_tracks - valid.sum()),
              "num_behind_camera": int((~result.in_front).sum()),
              "track_length_mean": float(kept.length.mean()) if kept.num_tracks else 0.0,
              "reprojection_error_normalized_median": float(np.median(error)) if error.size else None,
              **color_report, "time_s": time.perf_counter() - start}
    logger.info("triangulate: %d of %d tracks kept (%d points)", int(valid.sum()), tracks.num_tracks, int(valid.sum()))
    return structure, report
