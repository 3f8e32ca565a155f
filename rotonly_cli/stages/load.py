"""Stage `load`: INPUT (COLMAP database or OpenMVG project) -> SfMScene -> ViewGraph.

Relative poses (architecture.md "CLI contract"): a stored pose is kept only when it comes
from an essential matrix (COLMAP ``CALIBRATED``). Poses decomposed from a homography or a
fundamental matrix (``PLANAR``, ``UNCALIBRATED``, ``PLANAR_OR_PANORAMIC`` ...) are several
times less accurate (data/strecha/README.md), and OpenMVG stores none: those edges are
re-estimated from their inlier matches with pycolmap's calibrated LO-RANSAC
(``estimate_relative_pose``, formats.md §4.7) on normalized coordinates, seeded, keeping the
RANSAC inliers only. It is per-edge C++ work, so a loop over edges is fine here.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import InputKind, detect_input
from rotonly_cli.options import LoadOptions, Reestimate
from rotonly_cli.scene.types import Intrinsics, SfMScene
from rotonly_cli.scene.view_graph import Edge, ViewGraph, largest_component

logger = logging.getLogger(__name__)

#: configurations whose stored cam2_from_cam1 comes from an essential matrix (formats.md §4.5)
ESSENTIAL_CONFIGS = ("CALIBRATED", "E")

def read_input(input_path: str | Path, matches_dir: str | Path | None = None) -> tuple[SfMScene, str]:
    """(scene, kind) for a COLMAP database or an OpenMVG sfm_data.json (+ features, matches)."""
    from rotonly_cli.io import colmap, openmvg

    input_path = Path(input_path)
    kind = detect_input(input_path)
    if kind == InputKind.COLMAP_DB:
        return colmap.read_database(input_path), kind
    if kind == InputKind.OPENMVG:
        sfm_data = input_path / "sfm_data.json" if input_path.is_dir() else input_path
        scene = openmvg.read_project(sfm_data, matches_dir)
        if not scene.pairs:
            raise InputError("no matches file (matches.e/f/putative .bin|.txt) beside the features",
                             path=str(matches_dir or sfm_data.parent), field="--matches-dir")
        return scene, kind
    raise InputError("a COLMAP model holds no matches; give the COLMAP database or an OpenMVG sfm_data.json",
                     path=str(input_path))


def focal_length(intrinsics: Intrinsics) -> float:
    """Focal length in pixels (mean of fx, fy for two-focal COLMAP models)."""
    params = np.asarray(intrinsics.params, dtype=float).ravel()
    two_focal = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE",
                 "RAD_TAN_THIN_PRISM_FISHEYE")
    if intrinsics.model in two_focal:
        return float(params[:2].mean())
    return float(params[0])


def _relative_pose_ransac(x_i: np.ndarray, x_j: np.ndarray, focal_i: float, focal_j: float,
                          options: LoadOptions):
    """pycolmap LO-RANSAC on normalized points through SIMPLE_PINHOLE(f, 0, 0) cameras, so
    the threshold is in pixels. Returns (R_j_from_i, unit t, inlier mask) or None."""
    import pycolmap

    cameras = [pycolmap.Camera(model=pycolmap.CameraModelId.SIMPLE_PINHOLE, width=2, height=2,
                               params=np.array([f, 0.0, 0.0])) for f in (focal_i, focal_j)]
    ransac = pycolmap.RANSACOptions(max_error=options.ransac_max_error_px, random_seed=options.seed,
                                    min_num_trials=options.ransac_min_trials, confidence=options.ransac_confidence)
    result = pycolmap.estimate_relative_pose(cameras[0], np.ascontiguousarray(x_i * focal_i), cameras[1],
                                             np.ascontiguousarray(x_j * focal_j), ransac)
    if result is None:
        return None
    pose = result["cam2_from_cam1"]
    t = np.array(pose.translation, dtype=float)
    norm = np.linalg.norm(t)
    return (np.array(pose.rotation.matrix(), dtype=float), t / norm if norm > 0 else t,
            np.asarray(result["inlier_mask"], dtype=bool).ravel())


def build_view_graph(scene: SfMScene, options: LoadOptions = LoadOptions()) -> tuple[ViewGraph, dict]:
    """ViewGraph of the scene's pairs (re-estimating poses as the module docstring says),
    with the min-inlier filter and the largest-component check applied."""
    options.validate()
    start = time.perf_counter()
    graph = ViewGraph(views=dict(scene.views))
    to_estimate: list[int] = []
    for (i, j) in sorted(scene.pairs):
        pair = scene.pairs[(i, j)]
        matches = np.asarray(pair.matches, dtype=np.int64).reshape(-1, 2)
        has_pose = pair.R_j_from_i is not None and pair.verified
        essential = pair.config in ESSENTIAL_CONFIGS
        edge = Edge(i, j, np.asarray(pair.R_j_from_i, dtype=float) if has_pose else np.eye(3),
                    np.zeros(3) if pair.t_j_from_i is None else np.asarray(pair.t_j_from_i, dtype=float),
                    matches, pose_source="stored" if has_pose else "", config=pair.config)
        graph.edges.append(edge)
        if i not in scene.normalized or j not in scene.normalized:
            edge.filter("view without calibration")
        elif len(matches) < options.min_inliers:
            edge.filter("too few inliers")
        elif options.reestimate == Reestimate.ALL or (options.reestimate == Reestimate.AUTO
                                                      and not (has_pose and essential)):
            to_estimate.append(len(graph.edges) - 1)
        elif not has_pose:
            edge.filter("no relative pose")
    num_failed = 0

    def estimate_edge(k: int):
        edge = graph.edges[k]
        x_i = scene.normalized[edge.i][edge.matches[:, 0]]
        x_j = scene.normalized[edge.j][edge.matches[:, 1]]
        focal_i = focal_length(scene.intrinsics[scene.views[edge.i].intrinsics_id])
        focal_j = focal_length(scene.intrinsics[scene.views[edge.j].intrinsics_id])
        return _relative_pose_ransac(x_i, x_j, focal_i, focal_j, options)

    # pycolmap releases the GIL inside RANSAC: one thread per core; every edge has its own
    # seeded RANSAC, so the results do not depend on the scheduling
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1)) as pool:
        estimated = pool.map(estimate_edge, to_estimate)
        if options.progress:
            from rotonly_cli.runtime.progress import progress_bar

            estimated = progress_bar(estimated, total=len(to_estimate), desc="relative poses (RANSAC)", unit="edge")
        estimates = list(estimated)
    for k, estimate in zip(to_estimate, estimates):
        edge = graph.edges[k]
        if estimate is None:
            num_failed += 1
            edge.filter("relative pose estimation failed")
            continue
        edge.R_j_from_i, edge.t_dir, inliers = estimate
        edge.matches = edge.matches[inliers]
        edge.pose_source = "ransac"
    num_before = len(graph.active_edges())
    for k in graph.active_edges():
        if graph.edges[k].num_inliers < options.min_inliers:
            graph.edges[k].filter("too few inliers")
    num_few = num_before - len(graph.active_edges())
    component = largest_component(graph)
    report = {
        "num_views": len(scene.views), "num_pairs": len(scene.pairs), "num_reestimated": len(to_estimate),
        "num_ransac_failed": num_failed, "num_too_few_inliers_after_ransac": num_few,
        "num_active_edges": len(graph.active_edges()), "largest_component_views": len(component),
        "unregistered_views": list(graph.unregistered_views),
        "num_inlier_matches": int(sum(graph.edges[k].num_inliers for k in graph.active_edges())),
        "ransac_max_error_px": options.ransac_max_error_px, "min_inliers": options.min_inliers,
        "time_s": time.perf_counter() - start,
    }
    logger.info("view graph: %d views, %d pairs, %d re-estimated (%d failed), %d active edges, "
                "largest component %d views", len(scene.views), len(scene.pairs), len(to_estimate), num_failed,
                report["num_active_edges"], len(component))
    return graph, report
