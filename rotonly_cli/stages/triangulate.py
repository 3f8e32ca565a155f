"""Stage `triangulate`: tracks of all active edges between posed views, triangulated at
once (``geometry.triangulation``), coloured from the images when they can be found."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rotonly_cli.geometry.ligt import LiGTOptions, observation_errors, outlier_threshold_px
from rotonly_cli.geometry.track_split import split_conflicts
from rotonly_cli.geometry.tracks import (
    Tracks,
    compact_track_ids,
    gather_observations,
    in_tracks_of_two,
    tracks_from_arrays,
)
from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks
from rotonly_cli.io.images import image_file
from rotonly_cli.scene.ids import observation_lists
from rotonly_cli.scene.tracks import TrackCache, graph_tracks
from rotonly_cli.scene.types import SfMScene, Structure
from rotonly_cli.scene.view_graph import ViewGraph

logger = logging.getLogger(__name__)
GREY = 128
#: the reprojection threshold (px) that splits tracks merged by a wrong match when no
#: consistent track gives one: OpenMVG's 4 px outlier rule (TriangulationOptions)
SPLIT_FALLBACK_THRESHOLD_PX = 4.0


def _read_images(paths: list[Path], threads: int) -> Iterator[np.ndarray | None]:
    """BGR images in order (None where missing or unreadable); with ``threads`` > 1 decoded
    on that many threads (OpenCV releases the GIL while decoding). A generator, so only a
    few decoded images are alive at once."""
    import cv2

    def read(path: Path | None) -> np.ndarray | None:
        return None if path is None else cv2.imread(str(path), cv2.IMREAD_COLOR)

    if threads < 2 or len(paths) < 2:
        yield from map(read, paths)
        return
    with ThreadPoolExecutor(max_workers=min(len(paths), threads)) as pool:
        yield from pool.map(read, paths)


def _image_path(image_root: str | Path, name: str) -> Path | None:
    """The file to read for image ``name``, None when missing or not to be read: names that
    leave ``image_root`` or are not images are never opened (io/images), with a warning."""
    path, reason = image_file(image_root, name)
    if reason not in (None, "missing"):
        logger.warning("triangulate: image %r not read for the point colours: %s", name, reason)
    return path


def keypoint_colors(scene: SfMScene, image_root: str | Path, view_ids: list[int],
                    threads: int = os.cpu_count() or 1) -> dict[int, np.ndarray | None]:
    """RGB (n, 3) uint8 of every keypoint of each view, from the pixel holding it (COLMAP
    pixel convention: (u, v) lies in pixel floor(u), floor(v)); None where the image (or
    the keypoints) cannot be read."""
    readable, paths = _readable_images(scene, image_root, view_ids)
    colors: dict[int, np.ndarray | None] = dict.fromkeys(view_ids)
    for view_id, image in zip(readable, _read_images(paths, threads)):
        if image is not None:
            colors[view_id] = _pixel_colors(image, scene.keypoints[view_id])
    return colors


def _readable_images(scene: SfMScene, image_root: str | Path, view_ids: list[int]) -> tuple[list[int], list]:
    """The views of ``view_ids`` with keypoints, and the image file of each (None: not read)."""
    readable = [view_id for view_id in view_ids if view_id in scene.keypoints]
    return readable, [_image_path(image_root, scene.views[view_id].name) for view_id in readable]


def _pixel_colors(image: np.ndarray, keypoints) -> np.ndarray:
    """RGB (n, 3) uint8 of the pixels holding the keypoints (n, 2) of a BGR image."""
    pixels = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    u = np.clip(np.floor(pixels[:, 0]).astype(np.int64), 0, image.shape[1] - 1)
    v = np.clip(np.floor(pixels[:, 1]).astype(np.int64), 0, image.shape[0] - 1)
    return image[v, u, ::-1]  # OpenCV is BGR


class ForkedKeypointColors:
    """:func:`keypoint_colors` of ``view_ids``, decoded by a forked child
    (runtime.parallel.ForkedCall) into a shared buffer while this process goes on;
    :meth:`result` waits for it, like a Future's. A child leaves every later fork of this
    process safe (runtime.parallel.fork_safe), where a decoding thread would keep GRRM and
    TRRM in one process while it runs. Should the child die, the images are decoded here
    (ForkedCall), into the same buffer."""

    def __init__(self, scene: SfMScene, image_root: str | Path, view_ids: list[int]):
        from rotonly_cli.runtime.parallel import ForkedCall, shared_array

        self._scene, self._view_ids = scene, view_ids
        # the files are chosen here, so that their warnings are logged by this process
        self._readable, paths = _readable_images(scene, image_root, view_ids)
        sizes = [len(np.asarray(scene.keypoints[v]).reshape(-1, 2)) for v in self._readable]
        self._offsets = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)])
        self._rgb = shared_array((int(self._offsets[-1]), 3), np.uint8)
        self._decoded = shared_array((len(self._readable),), np.uint8)
        self._call = ForkedCall(lambda: self._decode(paths))
        self._colors: dict[int, np.ndarray | None] | None = None

    def _decode(self, paths: list) -> None:
        for row, (view_id, image) in enumerate(zip(self._readable, _read_images(paths, 1))):
            if image is not None:
                rows = slice(self._offsets[row], self._offsets[row + 1])
                self._rgb[rows] = _pixel_colors(image, self._scene.keypoints[view_id])
                self._decoded[row] = 1

    def result(self, timeout: float | None = None) -> dict[int, np.ndarray | None]:
        if self._colors is None:
            self._call.result(timeout)
            colors: dict[int, np.ndarray | None] = dict.fromkeys(self._view_ids)
            for row, view_id in enumerate(self._readable):
                if self._decoded[row]:
                    colors[view_id] = np.array(self._rgb[self._offsets[row]:self._offsets[row + 1]])
            self._colors = colors
        return self._colors


def point_colors(scene: SfMScene, image_root: str | Path | None, view_ids: list[int], obs_point: np.ndarray,
                 obs_view_row: np.ndarray, obs_feature: np.ndarray, num_points: int,
                 keypoint_rgb: dict[int, np.ndarray | None] | None = None) -> tuple[np.ndarray, dict]:
    """Mean RGB of each point over its observations' pixels; grey where no image could be
    read. ``keypoint_rgb``: :func:`keypoint_colors` of (at least) the observing views, if
    already computed."""
    sums = np.zeros((num_points, 3))
    hits = np.zeros(num_points)
    missing: list[str] = []
    if image_root is not None:
        by_view = np.argsort(obs_view_row, kind="stable")  # observations grouped by view
        rows, group_start = np.unique(obs_view_row[by_view], return_index=True)
        group_end = np.append(group_start[1:], len(by_view))
        observing = [view_ids[row] for row in rows.tolist()]
        if keypoint_rgb is None or any(view_id not in keypoint_rgb for view_id in observing):
            keypoint_rgb = keypoint_colors(scene, image_root, observing)
        rgb = np.zeros((len(obs_point), 3))
        coloured = np.zeros(len(obs_point), dtype=bool)
        for view_id, start, end in zip(observing, group_start.tolist(), group_end.tolist()):
            if keypoint_rgb[view_id] is None:
                missing.append(scene.views[view_id].name)
                continue
            observations = by_view[start:end]
            rgb[observations] = keypoint_rgb[view_id][obs_feature[observations]]
            coloured[observations] = True
        # sums of small integers: exact in any order (bincount is ~10x faster than add.at)
        for channel in range(3):
            sums[:, channel] = np.bincount(obs_point[coloured], weights=rgb[coloured, channel],
                                           minlength=num_points)
        hits = np.bincount(obs_point[coloured], minlength=num_points).astype(float)
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


def start_keypoint_colors(scene: SfMScene, image_root: str | Path | None) -> ForkedKeypointColors | Future | None:
    """:func:`keypoint_colors` of every view with keypoints, started now (None without an image
    folder): in a forked child where forking is safe (:class:`ForkedKeypointColors`), else on
    one background thread (OpenCV releases the GIL). ``rotonly run`` starts it right after
    loading: the keypoints are known then, and the JPEG decoding overlaps the rotation stages
    instead of the triangulation. The colours are the same pixels'."""
    if image_root is None:
        return None
    from rotonly_cli.runtime.parallel import fork_safe

    if fork_safe():
        return ForkedKeypointColors(scene, image_root, sorted(scene.keypoints))
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="keypoint-colors")
    future = executor.submit(keypoint_colors, scene, image_root, sorted(scene.keypoints), 1)
    executor.shutdown(wait=False)  # the thread ends with its one task
    return future


#: observations per --cluster task of the triangulation: ~2 us each (1000 views, 1 M
#: observations: 1.9 s, docs/results.md), so 2^18 of them are ~0.5 s of work
CLUSTER_TASK_OBSERVATIONS = 1 << 18


def _triangulate(R: np.ndarray, C: np.ndarray, obs_point: np.ndarray, obs_view: np.ndarray, obs_xy: np.ndarray,
                 num_points: int | None = None, options: TriangulationOptions | None = None,
                 with_parallax: bool = True):
    """geometry.triangulation.triangulate_tracks; with --cluster, on the cluster in tasks of
    consecutive tracks of about CLUSTER_TASK_OBSERVATIONS observations (every number of a
    point comes from its own observations: the same bits), the poses scattered once."""
    from rotonly_cli.runtime import cluster
    from rotonly_cli.runtime.parallel import chunk_ranges, concat_results

    session = cluster.active()
    obs_point = np.asarray(obs_point, dtype=np.int64)
    num_points = (int(obs_point.max()) + 1 if obs_point.size else 0) if num_points is None else num_points
    if session is None or num_points == 0:
        return triangulate_tracks(R, C, obs_point, obs_view, obs_xy, num_points, options, with_parallax)
    first = np.searchsorted(obs_point, np.arange(num_points + 1))  # each point's first observation
    ranges = chunk_ranges(np.diff(first), 0, num_points, CLUSTER_TASK_OBSERVATIONS)
    poses = session.scatter((np.asarray(R, dtype=float), np.asarray(C, dtype=float)), "triangulate")
    tasks = ((poses, obs_point[first[a]:first[b]] - a, obs_view[first[a]:first[b]], obs_xy[first[a]:first[b]],
              b - a, options, with_parallax) for a, b in ranges)
    parts = session.map("triangulate", _triangulate_task, tasks, len(ranges))
    return parts[0] if len(parts) == 1 else concat_results(parts)


def _triangulate_task(poses: tuple, obs_point, obs_view, obs_xy, num_points, options, with_parallax):
    """On a cluster worker: triangulate_tracks on the poses scattered and a task's tracks."""
    return triangulate_tracks(poses[0], poses[1], obs_point, obs_view, obs_xy, num_points, options, with_parallax)


def _keep_observations(tracks: Tracks, obs_xy: np.ndarray, keep: np.ndarray) -> tuple[Tracks, np.ndarray]:
    """The tracks without the observations where ``keep`` is False; tracks left with fewer
    than two observations go."""
    keep = in_tracks_of_two(tracks.track_id, keep)
    if keep.all():
        return tracks, obs_xy
    track_id = compact_track_ids(tracks.track_id[keep])[1]  # Tracks.track_id is grouped by track
    return (tracks_from_arrays(track_id, tracks.view[keep], tracks.feature[keep], tracks.num_inconsistent),
            obs_xy[keep])


def _sigma_by_camera(scene: SfMScene, view_ids: list[int], view_rows: np.ndarray, error_px: np.ndarray) -> dict:
    """Per camera (intrinsics id) the robust sigma (1.4826 x the median) of the reprojection
    errors (px) of its views' observations, before any is dropped: how well the camera's
    intrinsics fit (calibration/)."""
    camera_of_row = np.array([scene.views[v].intrinsics_id for v in view_ids], dtype=np.int64)
    cameras = camera_of_row[view_rows]
    return {str(int(c)): 1.4826 * float(np.median(error_px[cameras == c])) for c in np.unique(cameras)}


def posed_edges(graph: ViewGraph, R_cam_from_world: np.ndarray, centers: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """(per view row: has a rotation and a centre, the active edges between such views)."""
    view_ids = graph.view_ids()
    row_of = {v: r for r, v in enumerate(view_ids)}
    posed = np.all(np.isfinite(R_cam_from_world.reshape(len(view_ids), -1)), axis=1) & \
        np.all(np.isfinite(centers), axis=1)
    return posed, [k for k in graph.active_edges()
                   if posed[row_of[graph.edges[k].i]] and posed[row_of[graph.edges[k].j]]]


@dataclass
class TriangulatedTracks:
    """The tracks of the active edges between posed views that the triangulation keeps
    (:func:`triangulated_tracks`), with their points and the counts the report gives."""

    kept: Tracks  # the tracks with a valid point; Tracks.view holds view rows (graph.view_ids() order)
    points: np.ndarray  # (kept.num_tracks, 3) world points
    mean_error: np.ndarray  # (kept.num_tracks,) mean normalized reprojection error
    num_edges: int
    num_observations: int  # before the outlier test
    num_observations_dropped: int  # by the outlier test
    num_tracks: int  # after the outlier test, before the triangulation's checks
    num_behind_camera: int
    outlier_sigma_px: float
    outlier_threshold_px: float
    outlier_sigma_px_by_camera: dict
    split: dict | None = None  # geometry.track_split's counts, when tracks were split


def _with_split_parts(tracks: Tracks, obs_xy: np.ndarray, error_px: np.ndarray, R: np.ndarray, centers: np.ndarray,
                      per_view: list[np.ndarray], focal: np.ndarray, threshold_px: float):
    """(tracks, observations, errors in px) with the consistent parts of the components that
    see a view twice (geometry.track_split, at ``threshold_px``) appended as new tracks, and
    the split's report."""
    conflicts = tracks.conflicts
    xy = gather_observations(conflicts, per_view)
    C = np.where(np.isfinite(centers), centers, 0.0)
    split = split_conflicts(R, C, conflicts, xy, threshold_px / focal[conflicts.view])
    keep = split.part >= 0
    order = np.lexsort((conflicts.view[keep], split.part[keep]))  # tracks_from_arrays' order
    part, view = split.part[keep][order], conflicts.view[keep][order]
    part_xy = xy[keep][order]
    part_error = observation_errors(R, centers, part, view, part_xy, np.ones(part.size, dtype=bool),
                                    _triangulate) * focal[view]
    merged = tracks_from_arrays(np.concatenate([tracks.track_id, tracks.num_tracks + part]),
                                np.concatenate([tracks.view, view]),
                                np.concatenate([tracks.feature, conflicts.feature[keep][order]]),
                                tracks.num_inconsistent)
    return (merged, np.concatenate([obs_xy, part_xy]), np.concatenate([error_px, part_error]),
            {**split.report(), "num_observations": int(part.size)})


def triangulated_tracks(graph: ViewGraph, scene: SfMScene, R_cam_from_world: np.ndarray, centers: np.ndarray,
                        options: TriangulationOptions | None = None, track_cache: TrackCache | None = None,
                        outliers: LiGTOptions | None = None, split: bool = True) -> TriangulatedTracks:
    """The tracks of the active edges between posed views (gross outlier matches left out
    under the rotations, scene.tracks.graph_tracks), each observation tested against the
    rest of its track (``outliers``: the robust LiGT rounds' test, once), triangulated; the
    tracks with a valid point. ``split``: the components that see a view twice (a wrong
    match merged them) are cut into their consistent parts (geometry.track_split) at the
    threshold of that test, and the parts join the tracks; otherwise they are left out.
    Shared by :func:`triangulate_graph` and the reject stage's confirmation of matches by
    their tracks (stages/reject.py)."""
    outliers = outliers or LiGTOptions()
    view_ids = graph.view_ids()
    focal = scene.focal_px(view_ids)
    focal = np.where(np.isfinite(focal), focal, 1000.0)
    posed, edges = posed_edges(graph, R_cam_from_world, centers)
    R = np.where(posed[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, scene.normalized, edges, R, cache=track_cache, keep_conflicts=split)
    C = np.where(posed[:, None], centers, 0.0)
    centers_or_nan = np.where(posed[:, None], centers, np.nan)
    # the outlier test of the robust LiGT rounds (stages/translate): observations that
    # reproject badly against the rest of their track leave it before the final solve
    error = observation_errors(R, centers_or_nan, tracks.track_id, tracks.view, obs_xy,
                               np.ones(tracks.num_observations, dtype=bool), _triangulate) * focal[tracks.view]
    finite = np.isfinite(error)
    sigma, threshold = outlier_threshold_px(error[finite], outliers) if finite.any() else (np.nan, np.inf)
    split_report = None
    if split and tracks.conflicts is not None and tracks.conflicts.view.size:
        # the threshold is the consistent tracks' (their test is the same with or without the
        # split); when every component saw a view twice, the split's own parts give it
        per_view = [scene.normalized.get(v, np.zeros((0, 2))) for v in view_ids]
        tracks, obs_xy, error, split_report = _with_split_parts(
            tracks, obs_xy, error, R, centers_or_nan, per_view, focal,
            threshold if np.isfinite(threshold) else SPLIT_FALLBACK_THRESHOLD_PX)
        finite = np.isfinite(error)
        if not np.isfinite(threshold) and finite.any():
            sigma, threshold = outlier_threshold_px(error[finite], outliers)
    num_observations = tracks.num_observations
    camera_sigma = _sigma_by_camera(scene, view_ids, tracks.view[finite], error[finite])
    tracks, obs_xy = _keep_observations(tracks, obs_xy, error <= threshold)
    result = _triangulate(R, C, tracks.track_id, tracks.view, obs_xy, tracks.num_tracks, options)
    valid = result.valid
    return TriangulatedTracks(tracks.subset(valid), result.points_in_world[valid],
                              result.mean_reprojection_error[valid],
                              len(edges), num_observations, int(num_observations - tracks.num_observations),
                              tracks.num_tracks, int((~result.in_front).sum()), sigma, threshold, camera_sigma,
                              split_report)


def triangulate_graph(graph: ViewGraph, scene: SfMScene, R_cam_from_world: np.ndarray, centers: np.ndarray,
                      image_root: str | Path | None = None,
                      options: TriangulationOptions | None = None,
                      keypoint_rgb: ForkedKeypointColors | Future | dict[int, np.ndarray | None] | None = None,
                      track_cache: TrackCache | None = None,
                      outliers: LiGTOptions | None = None) -> tuple[Structure, dict]:
    """Structure (valid points only, observations as (view id, keypoint)) and report.

    ``outliers``: the outlier test (outlier_sigmas, min_outlier_threshold_px,
    max_drop_fraction) of the robust LiGT rounds, applied once to every observation.
    ``keypoint_rgb``: keypoint colours already being computed (:func:`start_keypoint_colors`)
    or computed; without them the images are decoded here, beside the triangulation.
    ``track_cache``: the run's, shared with translate (scene/tracks)."""
    start = time.perf_counter()
    view_ids = graph.view_ids()
    with ThreadPoolExecutor(max_workers=1) as pool:
        # JPEG decoding (for the colours) on a second thread while this one triangulates:
        # one decoder thread, the images of every view an edge touches, keypoint colours
        # only kept (no decoded image stays alive)
        colors_future = keypoint_rgb
        if colors_future is None and image_root is not None:
            edges = posed_edges(graph, R_cam_from_world, centers)[1]
            edge_views = sorted({graph.edges[k].i for k in edges} | {graph.edges[k].j for k in edges})
            colors_future = pool.submit(keypoint_colors, scene, image_root, edge_views, 1)
        solved = triangulated_tracks(graph, scene, R_cam_from_world, centers, options, track_cache, outliers)
        kept, points = solved.kept, solved.points
        keypoint_rgb = colors_future if isinstance(colors_future, dict | None) else colors_future.result()
    colors, color_report = point_colors(scene, image_root, view_ids, kept.track_id, kept.view, kept.feature,
                                        kept.num_tracks, keypoint_rgb)
    view_feature = np.stack([np.asarray(view_ids, dtype=np.int64)[kept.view],
                             np.asarray(kept.feature, dtype=np.int64)], axis=1).reshape(-1, 2)
    track_lengths = np.diff(np.asarray(kept.offsets, dtype=np.int64))
    structure = Structure(point_ids=np.arange(kept.num_tracks, dtype=np.int64), points=points, colors=colors,
                          observations=observation_lists(track_lengths, view_feature),
                          observation_arrays=(track_lengths, view_feature))
    error = solved.mean_error
    report = {"num_edges": solved.num_edges, "num_observations_dropped": solved.num_observations_dropped,
              "outlier_sigma_px": solved.outlier_sigma_px, "outlier_threshold_px": solved.outlier_threshold_px,
              "outlier_sigma_px_by_camera": solved.outlier_sigma_px_by_camera,
              "num_tracks": solved.num_tracks, "num_points": kept.num_tracks,
              "num_rejected": int(solved.num_tracks - kept.num_tracks),
              "num_behind_camera": solved.num_behind_camera,
              **({"split_tracks": solved.split} if solved.split is not None else {}),
              "track_length_mean": float(kept.length.mean()) if kept.num_tracks else 0.0,
              "reprojection_error_normalized_median": float(np.median(error)) if error.size else None,
              **color_report, "time_s": time.perf_counter() - start}
    logger.info("triangulate: %d of %d tracks kept (%d points)", kept.num_tracks, solved.num_tracks, kept.num_tracks)
    return structure, report
