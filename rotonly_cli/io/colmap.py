"""COLMAP databases and sparse models <-> rotonly dataclasses (formats.md §4).

Everything goes through pycolmap 4.2.1 (``Database``, ``Reconstruction``, ``Camera``): blob
layouts, pair ids and camera models are pycolmap's business, not re-implemented here. One
exception for speed: the sparse-model writer assembles ``points3D.bin`` (and the point links
of ``images.bin``) with numpy (formats.md §4.8) and has pycolmap read them back, compute the
errors and write the final model, instead of one Python object per point and observation.

Conventions kept at this boundary (architecture.md "Conventions", formats.md §4.3/§4.5):
- view id = COLMAP image id, intrinsics id = COLMAP camera id (COLMAP ids are > 0, so a scene
  with id 0 — OpenMVG — is shifted by +1 when written, see ``_id_offset``);
- keypoints stay in COLMAP's pixel convention (as stored), ``normalized`` comes from
  ``Camera.cam_from_img`` (pycolmap's own undistortion);
- a pair (i, j) has i = the smaller image id = COLMAP ``image1``; its inlier matches index
  (i, j) and the stored ``cam2_from_cam1`` is ``R_j_from_i`` / ``t_j_from_i``.

pycolmap's ``Database.open`` rewrites bookkeeping bytes of a database it opens even if only
reads follow (measured: the md5 of a Strecha DB changed), so inputs are read through a
temporary copy and are never touched.
"""

from __future__ import annotations

import logging
import os
import shutil
import sqlite3
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.io.detect import is_colmap_model, is_sqlite
from rotonly_cli.scene.ids import shift_ids
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, Structure, View

PathLike = str | os.PathLike
logger = logging.getLogger(__name__)

# Tables read_database needs (formats.md §4.1).
REQUIRED_TABLES = ("cameras", "images", "keypoints", "two_view_geometries")
# OpenMVG PairMatches.config -> COLMAP TwoViewGeometry config name (formats.md §4.5). A
# verified pair of unknown kind is written CALIBRATED: COLMAP skips UNDEFINED pairs.
_CONFIG_FROM_OPENMVG = {"E": "CALIBRATED", "F": "UNCALIBRATED", "H": "PLANAR", None: "CALIBRATED"}
# Verified-and-rejected configurations: not a usable pair.
_REJECTED_CONFIGS = ("UNDEFINED", "DEGENERATE", "WATERMARK")


def _pycolmap():
    import pycolmap  # lazy: the CLI stays fast for commands that never touch COLMAP

    return pycolmap


# ============================================================================ camera models

def to_colmap_intrinsics(intrinsics: Intrinsics) -> Intrinsics:
    """The nearest COLMAP camera model of an OpenMVG intrinsic (formats.md §4.4 mapping);
    COLMAP models pass through. Principal points are already in COLMAP's convention."""
    params = np.asarray(intrinsics.params, dtype=np.float64).ravel()
    model = intrinsics.model
    if model == "pinhole":  # f, cx, cy
        new_model, new_params = "SIMPLE_PINHOLE", params[:3]
    elif model == "pinhole_radial_k1":  # f, cx, cy, k1: x_d = x (1 + k1 r^2) in both tools
        new_model, new_params = "SIMPLE_RADIAL", params[:4]
    elif model == "pinhole_radial_k3":  # f, cx, cy, k1, k2, k3
        f, cx, cy, k1, k2, k3 = params[:6]
        if k3 == 0.0:
            new_model, new_params = "RADIAL", np.array([f, cx, cy, k1, k2])
        else:  # FULL_OPENCV radial (1 + k1 r2 + k2 r4 + k3 r6) / (1 + 0), no tangential
            new_model = "FULL_OPENCV"
            new_params = np.array([f, f, cx, cy, k1, k2, 0.0, 0.0, k3, 0.0, 0.0, 0.0])
    elif model == "pinhole_brown_t2":  # f, cx, cy, k1, k2, k3, t1, t2 (t1 = OpenCV p1)
        f, cx, cy, k1, k2, k3, t1, t2 = params[:8]
        if k3 == 0.0:
            new_model, new_params = "OPENCV", np.array([f, f, cx, cy, k1, k2, t1, t2])
        else:
            new_model = "FULL_OPENCV"
            new_params = np.array([f, f, cx, cy, k1, k2, t1, t2, k3, 0.0, 0.0, 0.0])
    elif model == "fisheye":  # f, cx, cy, k1..k4: theta_d = theta (1 + k1 theta^2 + ...)
        f, cx, cy = params[:3]
        new_model, new_params = "OPENCV_FISHEYE", np.concatenate([[f, f, cx, cy], params[3:7]])
    else:
        _pycolmap_camera(intrinsics)  # validates a COLMAP model name / param count
        return intrinsics
    return Intrinsics(intrinsics.id, new_model, intrinsics.width, intrinsics.height,
                      np.asarray(new_params, dtype=np.float64))


def _pycolmap_camera(intrinsics: Intrinsics, camera_id: int | None = None):
    pycolmap = _pycolmap()
    try:
        model_id = pycolmap.CameraModelId.__members__[intrinsics.model]
    except KeyError:
        raise InputError(f"unknown camera model {intrinsics.model!r}",
                         field=f"intrinsics[{intrinsics.id}].model") from None
    camera = pycolmap.Camera(model=model_id, width=int(intrinsics.width),
                             height=int(intrinsics.height),
                             params=np.asarray(intrinsics.params, dtype=np.float64).ravel())
    if not camera.verify_params():
        raise InputError(f"{intrinsics.model} needs {len(camera.params_info.split(','))} params, "
                         f"got {np.asarray(intrinsics.params).size}",
                         field=f"intrinsics[{intrinsics.id}].params")
    camera.camera_id = intrinsics.id if camera_id is None else camera_id
    return camera


def _exact_openmvg_intrinsics(intrinsics: Intrinsics) -> Intrinsics | None:
    """An OpenMVG model with the *same* projection as a COLMAP camera, or None.
    OpenMVG has one focal length, so fx != fy has no exact equivalent."""
    params = np.asarray(intrinsics.params, dtype=np.float64).ravel()
    model = intrinsics.model
    if model in ("PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV") and params[0] != params[1]:
        return None
    if model == "SIMPLE_PINHOLE":
        new = ("pinhole", params[:3])
    elif model == "PINHOLE":
        new = ("pinhole", params[[0, 2, 3]])
    elif model == "SIMPLE_RADIAL":
        new = ("pinhole_radial_k1", params[:4])
    elif model == "RADIAL":
        new = ("pinhole_radial_k3", np.concatenate([params[:5], [0.0]]))
    elif model == "OPENCV":  # brown_t2 distortion order k1, k2, k3, t1, t2
        new = ("pinhole_brown_t2", np.concatenate([params[[0, 2, 3, 4, 5]], [0.0], params[6:8]]))
    elif model == "OPENCV_FISHEYE":
        new = ("fisheye", np.concatenate([params[[0, 2, 3]], params[4:8]]))
    elif model == "FULL_OPENCV" and np.all(params[9:12] == 0.0):
        new = ("pinhole_brown_t2", params[[0, 2, 3, 4, 5, 8, 6, 7]])
    else:
        return None
    return Intrinsics(intrinsics.id, new[0], intrinsics.width, intrinsics.height,
                      np.asarray(new[1], dtype=np.float64))


def to_openmvg_scene(scene: SfMScene) -> SfMScene:
    """A copy of ``scene`` whose intrinsics are OpenMVG models (for ``io.openmvg`` writers).

    COLMAP cameras with an exact OpenMVG equivalent keep their keypoints. The others
    (fx != fy, models OpenMVG lacks) become an undistorted ``pinhole`` with
    f = (fx + fy) / 2 and the same principal point, and their keypoints (and stored
    landmark pixels) are re-rendered from ``normalized`` through it, so normalized
    coordinates — what rotonly uses — are unchanged.
    """
    intrinsics: dict[int, Intrinsics] = {}
    resampled: dict[int, Intrinsics] = {}
    for intrinsic_id, intrinsic in scene.intrinsics.items():
        if intrinsic.model.islower():  # already an OpenMVG model
            intrinsics[intrinsic_id] = intrinsic
            continue
        exact = _exact_openmvg_intrinsics(intrinsic)
        if exact is None:
            params = np.asarray(intrinsic.params, dtype=np.float64).ravel()
            camera = _pycolmap_camera(intrinsic)
            focal = float(np.mean([camera.focal_length_x, camera.focal_length_y]))
            exact = Intrinsics(intrinsic_id, "pinhole", intrinsic.width, intrinsic.height,
                               np.array([focal, camera.principal_point_x,
                                         camera.principal_point_y]))
            resampled[intrinsic_id] = exact
            logger.info("camera %d (%s %s) has no exact OpenMVG model: keypoints re-rendered "
                        "through an undistorted pinhole f=%.6g", intrinsic_id, intrinsic.model,
                        np.array2string(params, precision=6), focal)
        intrinsics[intrinsic_id] = exact
    keypoints = dict(scene.keypoints)
    for view_id, view in scene.views.items():
        target = resampled.get(view.intrinsics_id)
        if target is None or view_id not in keypoints:
            continue
        if view_id not in scene.normalized:
            raise InputError(f"view {view_id} has keypoints but no normalized coordinates",
                             field=f"views[{view_id}]")
        keypoints[view_id] = scene.normalized[view_id] * target.params[0] + target.params[1:3]
    structure = scene.structure
    if structure is not None and resampled and structure.observation_pixels is not None:
        structure = replace(structure, observation_pixels=None)  # re-derived from keypoints
    return replace(scene, intrinsics=intrinsics, keypoints=keypoints, structure=structure,
                   views=dict(scene.views), poses=dict(scene.poses),
                   normalized=dict(scene.normalized), pairs=dict(scene.pairs))


def colmap_to_openmvg(scene: SfMScene) -> SfMScene:
    """COLMAP-read scene -> scene for the OpenMVG writers: 0-based ids (scene/ids), OpenMVG
    camera models (:func:`to_openmvg_scene`)."""

    def down(ids) -> int:
        ids = list(ids)
        return -1 if ids and min(ids) >= 1 else 0

    point_ids = [] if scene.structure is None else np.asarray(scene.structure.point_ids).tolist()
    shifted = shift_ids(scene, down(scene.views), down(scene.intrinsics), down(point_ids))
    return to_openmvg_scene(shifted)


def normalize_keypoints(camera, keypoints: np.ndarray) -> np.ndarray:
    """(n, 2) COLMAP-convention pixels -> (n, 2) undistorted normalized coordinates, one
    batched ``Camera.cam_from_img`` call (pycolmap's own undistortion)."""
    keypoints = np.ascontiguousarray(keypoints, dtype=np.float64).reshape(-1, 2)
    if keypoints.shape[0] == 0:
        return np.zeros((0, 2))
    return np.asarray(camera.cam_from_img(keypoints), dtype=np.float64)


# ============================================================================ database: reading

def check_database(path: PathLike) -> Path:
    """InputError unless ``path`` is an existing SQLite file holding COLMAP's tables.
    Reads through sqlite's read-only mode, which never writes."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file", path=str(path))
    if not path.is_file():
        raise InputError("is not a file (expected a COLMAP database)", path=str(path))
    if not is_sqlite(path):
        raise InputError("not an SQLite file (expected a COLMAP database)", path=str(path))
    try:
        # immutable=1: no locks and no -wal/-shm sidecars next to the input (pycolmap
        # databases are in WAL mode, where even a read-only open would create them).
        connection = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1",
                                     uri=True)
        try:
            tables = {row[0] for row in connection.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
        finally:
            connection.close()
    except sqlite3.DatabaseError as exc:
        raise InputError(f"unreadable SQLite database ({exc})", path=str(path)) from None
    for table in REQUIRED_TABLES:
        if table not in tables:
            raise InputError("COLMAP database without this table", path=str(path), field=table)
    return path


@contextmanager
def _open_database_copy(path: Path) -> Iterator:
    """pycolmap Database on a private copy of ``path`` (the input stays byte-identical)."""
    pycolmap = _pycolmap()
    with tempfile.TemporaryDirectory(prefix="rotonly-db-") as scratch:
        copy = Path(scratch) / "database.db"
        shutil.copyfile(path, copy)
        wal = Path(f"{path}-wal")  # committed-but-not-checkpointed pages of a WAL database
        if wal.is_file():
            shutil.copyfile(wal, Path(f"{copy}-wal"))
        database = pycolmap.Database.open(str(copy))
        try:
            yield database
        finally:
            database.close()


def read_database(path: PathLike, include_unverified: bool = True) -> SfMScene:
    """COLMAP database -> SfMScene (formats.md §4.1-§4.6).

    Verified pairs come from ``two_view_geometries`` (inlier matches, config name and, when
    stored, ``cam2_from_cam1`` as R_j_from_i / unit t_j_from_i); pairs verified and rejected
    (UNDEFINED, DEGENERATE, WATERMARK or no inlier) are dropped; with
    ``include_unverified`` the raw ``matches`` of pairs never verified come with
    ``verified=False``.
    """
    pycolmap = _pycolmap()
    path = check_database(path)
    scene = SfMScene(source="colmap-db")
    with _open_database_copy(path) as database:
        cameras = {camera.camera_id: camera for camera in database.read_all_cameras()}
        for camera_id, camera in cameras.items():
            scene.intrinsics[camera_id] = Intrinsics(
                camera_id, camera.model.name, int(camera.width), int(camera.height),
                np.array(camera.params, dtype=np.float64))
        for image in database.read_all_images():
            image_id = int(image.image_id)
            if image.camera_id not in cameras:
                raise InputError(f"image {image_id} refers to missing camera {image.camera_id}",
                                 path=str(path), field="images")
            camera = cameras[image.camera_id]
            scene.views[image_id] = View(image_id, image.name, int(image.camera_id),
                                         width=int(camera.width), height=int(camera.height))
            if database.exists_keypoints(image_id):
                keypoints = np.asarray(database.read_keypoints(image_id))[:, :2]
            else:
                keypoints = np.zeros((0, 2))
            scene.keypoints[image_id] = keypoints.astype(np.float64)
            scene.normalized[image_id] = normalize_keypoints(camera, scene.keypoints[image_id])

        pair_ids, geometries = database.read_two_view_geometries()
        verified_pair_ids = set()
        num_rejected = 0
        for pair_id, geometry in zip(pair_ids, geometries):
            verified_pair_ids.add(int(pair_id))
            i, j = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))  # i < j, canonical
            config = pycolmap.TwoViewGeometryConfiguration(int(geometry.config)).name
            inliers = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            if config in _REJECTED_CONFIGS or inliers.shape[0] == 0:
                num_rejected += 1
                continue
            _check_match_indices(scene, i, j, inliers, path, "two_view_geometries")
            pair = PairMatches(i, j, inliers, config=config, verified=True)
            relative = geometry.cam2_from_cam1
            if relative is not None:
                pair.R_j_from_i = np.array(relative.rotation.matrix(), dtype=np.float64)
                # A direction (scale unknown, §4.5): PLANAR/H decompositions store |t| != 1.
                translation = np.array(relative.translation, dtype=np.float64)
                norm = np.linalg.norm(translation)
                pair.t_j_from_i = translation / norm if norm > 0 else translation
            scene.pairs[(i, j)] = pair
        if num_rejected:
            logger.info("%s: %d verified-and-rejected pairs skipped", path, num_rejected)

        if include_unverified:
            raw_pair_ids, raw_matches = database.read_all_matches()
            for pair_id, matches in zip(raw_pair_ids, raw_matches):
                if int(pair_id) in verified_pair_ids:
                    continue
                i, j = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))
                matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
                if matches.shape[0] == 0:
                    continue
                _check_match_indices(scene, i, j, matches, path, "matches")
                scene.pairs[(i, j)] = PairMatches(i, j, matches, verified=False)
    scene.pairs = dict(sorted(scene.pairs.items()))
    return scene


def _check_match_indices(scene: SfMScene, i: int, j: int, matches: np.ndarray, path: Path,
                         table: str) -> None:
    for view_id, column in ((i, 0), (j, 1)):
        if view_id not in scene.views:
            raise InputError(f"pair ({i}, {j}) refers to missing image {view_id}",
                             path=str(path), field=table)
        if matches.shape[0] and (matches[:, column].max() >= len(scene.keypoints[view_id])):
            raise InputError(f"pair ({i}, {j}): keypoint index {int(matches[:, column].max())} "
                             f">= {len(scene.keypoints[view_id])} keypoints of image {view_id}",
                             path=str(path), field=table)


# ============================================================================ database: writing

def _id_offset(ids) -> int:
    """COLMAP ids must be > 0 (formats.md §4.2): shift a 0-based id set by +1."""
    ids = list(ids)
    return 1 - min(ids) if ids and min(ids) < 1 else 0


def write_database(path: PathLike, scene: SfMScene) -> None:
    """SfMScene -> new COLMAP database at ``path`` (replaced atomically).

    One camera per intrinsic (OpenMVG models mapped by ``to_colmap_intrinsics``), a trivial
    rig per camera and frame per image, keypoints, ``matches`` for every pair and a
    ``two_view_geometries`` row (inliers = the pair's matches, config, ``cam2_from_cam1``
    when known) for verified pairs. View/camera ids < 1 are shifted (``_id_offset``).
    """
    pycolmap = _pycolmap()
    path = Path(path)
    view_offset = _id_offset(scene.views)
    camera_offset = _id_offset(scene.intrinsics)
    with atomic.file_path(path, ".db", create=False, sidecars=("-journal", "-wal", "-shm")) as staging:
        database = pycolmap.Database.open(str(staging))
        try:
            _fill_database(pycolmap, database, scene, view_offset, camera_offset)
        finally:
            database.close()
        # pycolmap leaves the file in WAL mode, where every later reader (even read-only)
        # creates -wal/-shm files beside it; a rollback-journal file is self-contained.
        connection = sqlite3.connect(str(staging))
        try:
            connection.execute("PRAGMA journal_mode=DELETE")
        finally:
            connection.close()


def _default_camera(pycolmap, view: View, camera_id: int):
    """A camera for a view whose intrinsic is unknown: COLMAP's no-EXIF default (§4.4)."""
    width, height = int(view.width or 0), int(view.height or 0)
    if width <= 0 or height <= 0:
        raise InputError("view without intrinsic nor image size", field=f"views[{view.id}]")
    camera = pycolmap.Camera.create_from_model_name(camera_id, "SIMPLE_RADIAL",
                                                    1.2 * max(width, height), width, height)
    return camera


def _fill_database(pycolmap, database, scene: SfMScene, view_offset: int,
                   camera_offset: int) -> None:
    camera_ids: dict[int, int] = {}
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = to_colmap_intrinsics(scene.intrinsics[intrinsic_id])
        camera = _pycolmap_camera(intrinsic, intrinsic_id + camera_offset)
        camera.has_prior_focal_length = True  # calibrated: COLMAP then keeps E-based geometry
        camera_ids[intrinsic_id] = database.write_camera(camera, use_camera_id=True)
    next_camera_id = max(camera_ids.values(), default=0) + 1
    for view_id in sorted(scene.views):
        view = scene.views[view_id]
        if view.intrinsics_id not in camera_ids:
            camera = _default_camera(pycolmap, view, next_camera_id)
            camera_ids[view.intrinsics_id] = database.write_camera(camera, use_camera_id=True)
            next_camera_id += 1
    for camera_id in sorted(set(camera_ids.values())):
        rig = pycolmap.Rig(rig_id=camera_id)
        rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id))
        database.write_rig(rig, use_rig_id=True)
    for view_id in sorted(scene.views):
        view = scene.views[view_id]
        image_id = view_id + view_offset
        camera_id = camera_ids[view.intrinsics_id]
        image = pycolmap.Image(name=view.name, camera_id=camera_id, image_id=image_id)
        database.write_image(image, use_image_id=True)
        frame = pycolmap.Frame(frame_id=image_id, rig_id=camera_id)
        frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA,
                                                             camera_id), image_id))
        database.write_frame(frame, use_frame_id=True)
        keypoints = scene.keypoints.get(view_id)
        if keypoints is not None:
            database.write_keypoints(image_id, np.ascontiguousarray(keypoints, dtype=np.float32)
                                     .reshape(-1, 2))
    for (i, j), pair in sorted(scene.pairs.items()):
        if i not in scene.views or j not in scene.views:
            raise InputError(f"pair ({i}, {j}) refers to a missing view", field="pairs")
        matches = np.ascontiguousarray(pair.matches, dtype=np.uint32).reshape(-1, 2)
        id1, id2 = i + view_offset, j + view_offset
        database.write_matches(id1, id2, matches)  # i < j: stored as given (§4.3)
        if not pair.verified:
            continue
        geometry = pycolmap.TwoViewGeometry()
        config = _CONFIG_FROM_OPENMVG.get(pair.config, pair.config)
        if config not in pycolmap.TwoViewGeometryConfiguration.__members__:
            raise InputError(f"unknown two-view configuration {pair.config!r}",
                             field=f"pairs[({i}, {j})].config")
        geometry.config = pycolmap.TwoViewGeometryConfiguration.__members__[config]
        geometry.inlier_matches = matches
        if pair.R_j_from_i is not None:
            translation = (np.zeros(3) if pair.t_j_from_i is None
                           else np.asarray(pair.t_j_from_i, dtype=np.float64).reshape(3))
            geometry.cam2_from_cam1 = pycolmap.Rigid3d(
                pycolmap.Rotation3d(np.asarray(pair.R_j_from_i, dtype=np.float64)), translation)
        database.write_two_view_geometry(id1, id2, geometry)


# ============================================================================ sparse model

def _reconstruction(pycolmap, scene: SfMScene, posed: list[int], extra_points2D: dict[int, np.ndarray]):
    """pycolmap.Reconstruction of the cameras and posed views of ``scene`` (points2D = the
    view's keypoints, then ``extra_points2D``), without 3D points."""
    reconstruction = pycolmap.Reconstruction()
    view_offset = _id_offset(scene.views)
    camera_offset = _id_offset(scene.intrinsics)
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = to_colmap_intrinsics(scene.intrinsics[intrinsic_id])
        reconstruction.add_camera_with_trivial_rig(
            _pycolmap_camera(intrinsic, intrinsic_id + camera_offset))
    for view_id in posed:
        view = scene.views[view_id]
        if view.intrinsics_id not in scene.intrinsics:
            raise InputError("posed view without intrinsic", field=f"views[{view_id}]")
        pose = scene.poses[view_id]
        R = np.asarray(pose.R_cam_from_world, dtype=np.float64)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ np.asarray(
            pose.center, dtype=np.float64).reshape(3))
        keypoints = scene.keypoints.get(view_id)
        keypoints = (np.zeros((0, 2)) if keypoints is None
                     else np.asarray(keypoints, dtype=np.float64).reshape(-1, 2))
        image = pycolmap.Image(name=view.name, keypoints=np.concatenate([keypoints, extra_points2D[view_id]]),
                               camera_id=view.intrinsics_id + camera_offset,
                               image_id=view_id + view_offset)
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
    return reconstruction


@dataclass
class _ModelPoints:
    """3D points in COLMAP terms, tracks flattened: per point ``point3D_ids``, ``xyz``,
    ``colors``, ``track_lengths``; per track element ``image_ids``, ``point2D_indices``."""

    point3D_ids: np.ndarray
    xyz: np.ndarray
    colors: np.ndarray
    track_lengths: np.ndarray
    image_ids: np.ndarray
    point2D_indices: np.ndarray


def _model_points(scene: SfMScene, posed: list[int]) -> tuple[_ModelPoints, dict[int, np.ndarray]]:
    """Tracks of ``scene.structure`` restricted to posed views, and per posed view the extra
    points2D appended after its keypoints: observations whose keypoint index is out of
    range get the stored landmark pixel (or the projection), once per (view, index), in
    order of first use. Observations in unposed views are left out; points left without
    observations are not in the model."""
    extra_points2D = {view_id: np.zeros((0, 2)) for view_id in posed}
    structure = scene.structure
    if structure is None or not posed:  # no posed view: no 3D point is in the model
        empty = np.zeros(0, dtype=np.int64)
        return _ModelPoints(empty, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), empty, empty, empty), extra_points2D
    track_lengths, view_feature = structure.flat_observations()
    point_of_observation = np.repeat(np.arange(len(track_lengths)), track_lengths)
    posed_ids = np.asarray(posed, dtype=np.int64)
    num_keypoints = np.array([0 if scene.keypoints.get(view_id) is None else len(scene.keypoints[view_id])
                              for view_id in posed], dtype=np.int64)
    view_row = np.minimum(np.searchsorted(posed_ids, view_feature[:, 0]), len(posed) - 1)
    in_model = posed_ids[view_row] == view_feature[:, 0]
    features = view_feature[:, 1]
    point2D_indices = features.copy()
    is_extra = in_model & ((features < 0) | (features >= num_keypoints[view_row]))
    extra_observations = np.flatnonzero(is_extra)
    if extra_observations.size:  # rare (not in the pipeline): a Python loop is fine
        row_in_track = np.arange(len(view_feature)) - np.repeat(np.cumsum(track_lengths) - track_lengths,
                                                                track_lengths)
        first_use: dict[tuple[int, int], int] = {}
        extras: dict[int, list[np.ndarray]] = {view_id: [] for view_id in posed}
        for observation in extra_observations.tolist():
            key = (int(view_feature[observation, 0]), int(features[observation]))
            if key not in first_use:
                view_id = key[0]
                first_use[key] = int(num_keypoints[view_row[observation]]) + len(extras[view_id])
                extras[view_id].append(_observation_pixel(scene, int(point_of_observation[observation]),
                                                          int(row_in_track[observation])).reshape(1, 2))
            point2D_indices[observation] = first_use[key]
        extra_points2D.update({view_id: np.concatenate(blocks) for view_id, blocks in extras.items() if blocks})

    in_model_per_point = np.bincount(point_of_observation[in_model], minlength=len(track_lengths))
    kept = in_model_per_point > 0
    point_ids = np.asarray(structure.point_ids, dtype=np.int64).reshape(-1)
    point_offset = _id_offset(point_ids.tolist())
    colors = (np.zeros((len(track_lengths), 3), np.uint8) if structure.colors is None
              else np.asarray(structure.colors, dtype=np.uint8).reshape(-1, 3))
    view_offset = _id_offset(scene.views)
    points = _ModelPoints(
        point3D_ids=point_ids[kept] + point_offset,
        xyz=np.asarray(structure.points, dtype=np.float64).reshape(-1, 3)[kept],
        colors=colors[kept], track_lengths=in_model_per_point[kept],
        image_ids=view_feature[in_model, 0] + view_offset, point2D_indices=point2D_indices[in_model])
    return points, extra_points2D


# points3D.bin record head (formats.md §4.8): id, xyz, rgb, error, track length
_POINT3D_HEAD = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"),
                          ("track_length", "<u8")])
_TRACK_ELEMENT = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])
_POINT2D = np.dtype([("xy", "<f8", 2), ("point3D_id", "<u8")])


def _points3D_bin(points: _ModelPoints) -> bytes:
    """points3D.bin with the given tracks and ERROR -1 (recomputed by pycolmap), assembled
    with numpy: one record = head, then track elements (formats.md §4.8)."""
    num_points = len(points.point3D_ids)
    heads = np.zeros(num_points, dtype=_POINT3D_HEAD)
    heads["id"], heads["xyz"], heads["rgb"] = points.point3D_ids, points.xyz, points.colors
    heads["error"], heads["track_length"] = -1.0, points.track_lengths
    elements = np.zeros(len(points.image_ids), dtype=_TRACK_ELEMENT)
    elements["image_id"], elements["point2D_idx"] = points.image_ids, points.point2D_indices
    head_size, element_size = _POINT3D_HEAD.itemsize, _TRACK_ELEMENT.itemsize
    record_start = 8 + head_size * np.arange(num_points) + element_size * (
        np.cumsum(points.track_lengths) - points.track_lengths)
    payload = np.zeros(8 + head_size * num_points + element_size * len(elements), dtype=np.uint8)
    payload[:8] = np.frombuffer(np.uint64(num_points).tobytes(), dtype=np.uint8)
    payload[(record_start[:, None] + np.arange(head_size)).reshape(-1)] = heads.view(np.uint8)
    element_start = (np.repeat(record_start + head_size, points.track_lengths)
                     + element_size * (np.arange(len(elements)) - np.repeat(
                         np.cumsum(points.track_lengths) - points.track_lengths, points.track_lengths)))
    payload[(element_start[:, None] + np.arange(element_size)).reshape(-1)] = elements.view(np.uint8)
    return payload.tobytes()


def _link_points2D(images_bin: bytes, points: _ModelPoints) -> bytes:
    """images.bin as pycolmap wrote it (no 3D points) with each track element's point2D
    pointing at its 3D point. A keypoint claimed by two points is an error (pycolmap's
    AddPoint3D refuses it too)."""
    payload = bytearray(images_bin)
    point3D_of_element = np.repeat(points.point3D_ids, points.track_lengths).astype(np.uint64)
    by_image = np.argsort(points.image_ids, kind="stable")  # track elements grouped by image
    sorted_image_ids = points.image_ids[by_image]
    (num_images,), offset = np.frombuffer(payload, "<u8", 1, 0), 8
    for _ in range(int(num_images)):
        image_id = int(np.frombuffer(payload, "<u4", 1, offset)[0])
        offset += 4 + 7 * 8 + 4  # id, qw qx qy qz tx ty tz, camera id
        offset = payload.index(b"\0", offset) + 1  # NUL-terminated name
        num_points2D = int(np.frombuffer(payload, "<u8", 1, offset)[0])
        offset += 8
        points2D = np.frombuffer(payload, _POINT2D, num_points2D, offset)  # a view: writes go to payload
        mine = by_image[np.searchsorted(sorted_image_ids, image_id, "left"):
                        np.searchsorted(sorted_image_ids, image_id, "right")]
        if mine.size:
            point2D_indices, point3D_ids = points.point2D_indices[mine], point3D_of_element[mine]
            order = np.lexsort((point3D_ids, point2D_indices))
            point2D_indices, point3D_ids = point2D_indices[order], point3D_ids[order]
            claimed_twice = (point2D_indices[1:] == point2D_indices[:-1]) & (point3D_ids[1:] != point3D_ids[:-1])
            if np.any(claimed_twice):
                index = int(point2D_indices[1:][claimed_twice][0])
                raise InputError(f"keypoint {index} of image {image_id} observed by two 3D points",
                                 field="structure.observations")
            points2D["point3D_id"][point2D_indices] = point3D_ids
        offset += num_points2D * _POINT2D.itemsize
    return bytes(payload)


def _model_reconstruction(pycolmap, scene: SfMScene, workdir: Path):
    """The sparse model of ``scene`` as a pycolmap.Reconstruction: cameras and images built
    with pycolmap, the 3D points written as points3D.bin with numpy (no Python object per
    point or track element) and read back by pycolmap (its reader links everything)."""
    posed = [view_id for view_id in sorted(scene.views) if view_id in scene.poses]
    points, extra_points2D = _model_points(scene, posed)
    _reconstruction(pycolmap, scene, posed, extra_points2D).write_binary(str(workdir))
    images_path = workdir / "images.bin"
    images_path.write_bytes(_link_points2D(images_path.read_bytes(), points))
    (workdir / "points3D.bin").write_bytes(_points3D_bin(points))
    reconstruction = pycolmap.Reconstruction(str(workdir))
    reconstruction.update_point_3d_errors()  # points3D ERROR = mean reprojection error (px)
    return reconstruction


def _observation_pixel(scene: SfMScene, point_index: int, row: int) -> np.ndarray:
    structure = scene.structure
    assert structure is not None
    if structure.observation_pixels is not None:
        return np.asarray(structure.observation_pixels[point_index][row], dtype=np.float64)
    view_id, feature = structure.observations[point_index][row]
    intrinsic = to_colmap_intrinsics(scene.intrinsics[scene.views[view_id].intrinsics_id])
    pose = scene.poses[view_id]
    point_in_camera = pose.R_cam_from_world @ (structure.points[point_index] - pose.center)
    camera = _pycolmap_camera(intrinsic)
    return np.asarray(camera.img_from_cam(point_in_camera.reshape(1, 3)), dtype=np.float64)[0]


def write_model(out_dir: PathLike, scene: SfMScene, binary: bool = True) -> None:
    """Write the posed views of ``scene`` as a COLMAP sparse model (cameras, images, points3D,
    rigs, frames; binary or text). Views without a pose are omitted. Staged in a temporary
    folder beside ``out_dir``: a new ``out_dir`` appears by one rename, an existing one
    receives the files one rename each."""
    pycolmap = _pycolmap()
    out_dir = Path(out_dir)
    with atomic.filling_dir(out_dir) as staging:
        with tempfile.TemporaryDirectory(prefix=f".{out_dir.name}.points.", dir=out_dir.parent) as workdir:
            reconstruction = _model_reconstruction(pycolmap, scene, Path(workdir))
        if binary:
            reconstruction.write_binary(str(staging))
        else:
            reconstruction.write_text(str(staging))


def read_model(path: PathLike) -> SfMScene:
    """COLMAP sparse model folder -> SfMScene with cameras, (registered) views, poses,
    keypoints = the images' points2D, normalized, and structure with tracks and colours."""
    pycolmap = _pycolmap()
    path = Path(path)
    if not path.exists():
        raise InputError("no such folder", path=str(path))
    if not is_colmap_model(path):
        raise InputError("not a COLMAP model (needs cameras, images, points3D .bin or .txt)",
                         path=str(path))
    try:
        reconstruction = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError on corrupt files
        raise InputError(f"pycolmap cannot read the model ({exc})", path=str(path)) from None
    scene = SfMScene(source="colmap-model")
    for camera_id, camera in reconstruction.cameras.items():
        scene.intrinsics[int(camera_id)] = Intrinsics(
            int(camera_id), camera.model.name, int(camera.width), int(camera.height),
            np.array(camera.params, dtype=np.float64))
    for image_id in sorted(reconstruction.images):
        image = reconstruction.images[image_id]
        camera = reconstruction.cameras[image.camera_id]
        scene.views[int(image_id)] = View(int(image_id), image.name, int(image.camera_id),
                                          width=int(camera.width), height=int(camera.height))
        points = image.points2D
        keypoints = (np.array([p.xy for p in points], dtype=np.float64).reshape(-1, 2)
                     if len(points) else np.zeros((0, 2)))
        scene.keypoints[int(image_id)] = keypoints
        scene.normalized[int(image_id)] = normalize_keypoints(camera, keypoints)
        if image.has_pose:
            cam_from_world = image.cam_from_world()
            R = np.array(cam_from_world.rotation.matrix(), dtype=np.float64)
            t = np.array(cam_from_world.translation, dtype=np.float64)
            scene.poses[int(image_id)] = Pose(R, -R.T @ t)
    point_ids = sorted(reconstruction.points3D)
    if point_ids:
        points3D = [reconstruction.points3D[point_id] for point_id in point_ids]
        scene.structure = Structure(
            point_ids=np.array(point_ids, dtype=np.int64),
            points=np.array([p.xyz for p in points3D], dtype=np.float64).reshape(-1, 3),
            colors=np.array([p.color for p in points3D], dtype=np.uint8).reshape(-1, 3),
            observations=[[(int(e.image_id), int(e.point2D_idx)) for e in p.track.elements]
                          for p in points3D])
    return scene
