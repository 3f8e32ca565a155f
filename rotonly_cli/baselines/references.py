"""External and library reference methods for the benchmarks (not on ``rotonly run``'s path).

* :func:`chatterjee` — Chatterjee & Govindu L1RA + IRLS with the ℓ½ (HALF_NORM) weight, the
  TPAMI-2018 setting the paper and ROBA use as initialiser (algorithms.md §2.1 item 6), via
  :func:`rotonly_cli.geometry.averaging.average_rotations`, uniform edge weights (ROBA's
  ``AverageSO3Graph(..., 'Method', 'L0.5')`` has none).
* :func:`pycolmap_rotation_averaging` — ``pycolmap.run_rotation_averaging`` (algorithms.md §2.3),
  default options (Geman–McClure σ = 5°), edges weighted by ``num_matches`` for the spanning tree.
* :func:`pycolmap_global_mapper` — ``pycolmap.global_mapping`` (GLOMAP: rotation averaging +
  global positioning + bundle adjustment) on a private copy of a COLMAP database, intrinsics
  fixed (formats.md §4.7), as the Strecha README's reference row; optionally on given pairs
  only (their relative poses and inlier matches), as ``rotonly bench strecha`` runs it.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from rotonly_cli.geometry.averaging import AveragingOptions, RobustWeight, average_rotations


def chatterjee(num_views: int, edge_views: np.ndarray, R_j_from_i: np.ndarray, fixed_view: int = 0,
               weights: np.ndarray | None = None) -> np.ndarray:
    """Global R_cam_from_world (n, 3, 3) by L1RA + ℓ½-IRLS; NaN for views not connected."""
    edge_views = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
    options = AveragingOptions(weight_type=RobustWeight.HALF_NORM)
    result = average_rotations(num_views, edge_views[:, 0], edge_views[:, 1], R_j_from_i, weights=weights,
                               fixed_view=fixed_view, options=options)
    return result.R_cam_from_world


def pycolmap_rotation_averaging(num_views: int, edge_views: np.ndarray, R_j_from_i: np.ndarray,
                                num_matches: np.ndarray | None = None, weight_type: str = "GEMAN_MCCLURE",
                                seed: int = 0, weighted: bool = False) -> np.ndarray:
    """``pycolmap.run_rotation_averaging`` on the relative rotations (algorithms.md §2.3);
    ``weighted``: ``reweighting = INLIER_MATCH_COUNT``. (n, 3, 3), NaN if unregistered."""
    import pycolmap

    edge_views = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_id(
        1, pycolmap.CameraModelId.PINHOLE, 800.0, 1000, 1000))
    for v in range(num_views):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{v}", camera_id=1, image_id=v + 1))
    graph = pycolmap.PoseGraph()
    for e, (i, j) in enumerate(edge_views):
        edge = pycolmap.PoseGraphEdge(pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R_j_from_i[e])),
                                                       np.zeros(3)))
        edge.num_matches = int(num_matches[e]) if num_matches is not None else 100
        graph.add_edge(int(i) + 1, int(j) + 1, edge)
    options = pycolmap.RotationEstimatorOptions()
    options.weight_type = getattr(pycolmap.RotationWeightType, weight_type)
    options.random_seed = int(seed)
    if weighted:
        options.reweighting = pycolmap.RotationAveragingReweighting.INLIER_MATCH_COUNT
    out = np.full((num_views, 3, 3), np.nan)
    if not pycolmap.run_rotation_averaging(options, graph, rec, []):
        return out
    for v in range(num_views):
        image = rec.images[v + 1]
        if image.has_pose:
            out[v] = np.asarray(image.cam_from_world().rotation.matrix())
    return out


def pycolmap_global_mapper(database_path: str | Path, seed: int = 0, num_threads: int = 1,
                           pairs: dict | None = None) -> dict[str, np.ndarray]:
    """GLOMAP through pycolmap on a copy of ``database_path``: {image name: R_cam_from_world} of
    the largest model (intrinsics kept fixed). Returns {} when no model is produced.
    ``pairs``: {(image name i, image name j): (R_j_from_i, unit t_ij, inlier matches (m, 2) as
    keypoint indices [i, j])}: the copy's verified pairs are replaced by these, each a calibrated
    two-view geometry with that pose (E = [t]x R, which the mapper decomposes back into it) and
    those inliers, so that the mapper starts from the same pairs as the methods it is compared with."""
    import pycolmap

    previous_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # glog: errors only (GLOMAP logs every stage and missing image)
    try:
        return _global_mapper(pycolmap, database_path, seed, num_threads, pairs)
    finally:
        pycolmap.logging.minloglevel = previous_level


def _write_pairs(pycolmap, database_path: Path, pairs: dict) -> None:
    """Replace the verified pairs (two_view_geometries) of the database by ``pairs``."""
    database = pycolmap.Database.open(str(database_path))
    try:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        database.clear_two_view_geometries()
        for (name_i, name_j), (R, t, matches) in pairs.items():
            R, t = np.asarray(R, dtype=float), np.asarray(t, dtype=float)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
            geometry.E = skew @ R
            geometry.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
            geometry.inlier_matches = np.ascontiguousarray(matches, dtype=np.uint32)
            database.write_two_view_geometry(ids[name_i], ids[name_j], geometry)
    finally:
        database.close()


def global_mapper_options(pycolmap, seed: int, num_threads: int):
    """``pycolmap.GlobalPipelineOptions`` of the reference global mapper: seeded, on
    ``num_threads`` threads, the intrinsics held in its bundle adjustment (formats.md §4.7)."""
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = options.mapper.random_seed = int(seed)
    options.num_threads = options.mapper.num_threads = int(num_threads)
    bundle_adjustment = options.mapper.bundle_adjustment
    bundle_adjustment.refine_focal_length = False
    bundle_adjustment.refine_principal_point = False
    bundle_adjustment.refine_extra_params = False
    return options


def _global_mapper(pycolmap, database_path, seed: int, num_threads: int, pairs: dict | None) -> dict[str, np.ndarray]:
    with tempfile.TemporaryDirectory(prefix="rotonly_glomap_") as tmp:
        db_copy = Path(tmp) / "database.db"
        shutil.copyfile(database_path, db_copy)
        if pairs is not None:
            _write_pairs(pycolmap, db_copy, pairs)
        options = global_mapper_options(pycolmap, seed, num_threads)
        (Path(tmp) / "images").mkdir()  # must exist; the images themselves are not read
        (Path(tmp) / "out").mkdir()
        models = pycolmap.global_mapping(db_copy, Path(tmp) / "images", Path(tmp) / "out", options)
        if not models:
            return {}
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        return {image.name: np.asarray(image.cam_from_world().rotation.matrix())
                for image in rec.images.values() if image.has_pose}
