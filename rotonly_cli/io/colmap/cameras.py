"""COLMAP camera models <-> OpenMVG's, through pycolmap (formats.md §4.4), and the
COLMAP -> OpenMVG scene conversion."""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import replace

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.inputs import check_camera
from rotonly_cli.scene.ids import shift_ids
from rotonly_cli.scene.types import Intrinsics, SfMScene

PathLike = str | os.PathLike
logger = logging.getLogger(__name__)


def import_pycolmap():
    import pycolmap  # lazy: the CLI stays fast for commands that never touch COLMAP

    # pycolmap's own log lines (glog warnings such as "Failed to open database ... Trying next
    # registered factory") would precede rotonly's one-line errors; rotonly reports for it
    pycolmap.logging.minloglevel = max(pycolmap.logging.minloglevel, 2)  # errors only
    return pycolmap


# ============================================================================ camera models

@functools.cache
def colmap_camera_models() -> dict[int, tuple[str, int, tuple[int, ...], tuple[int, ...]]]:
    """COLMAP model id -> (name, number of params, focal length indices, principal point
    indices), from pycolmap itself (formats.md §4.4)."""
    pycolmap = import_pycolmap()
    models = {}
    for name, model in pycolmap.CameraModelId.__members__.items():
        if int(model) < 0:  # INVALID
            continue
        camera = pycolmap.Camera.create_from_model_id(1, model, 1.0, 2, 2)
        models[int(model)] = (name, len(camera.params), tuple(camera.focal_length_idxs()),
                              tuple(camera.principal_point_idxs()))
    return models


def check_colmap_camera(path: PathLike | None, field: str, model: str, width, height, params) -> None:
    """io/inputs.check_camera for a COLMAP camera ``model`` (name) with ``params`` (its
    parameter count must be right: the callers check it against the blob size)."""
    models = {name: entry for name, *entry in colmap_camera_models().values()}
    _, focal, principal = models[model]
    params = np.asarray(params, dtype=np.float64).ravel()
    if not principal:  # EQUIRECTANGULAR: no focal length, no principal point
        check_camera(path, field, width, height, [], [0.0, 0.0], params)
        return
    check_camera(path, field, width, height, params[list(focal)], params[list(principal)], params)


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
        pycolmap_camera(intrinsics)  # validates a COLMAP model name / param count
        return intrinsics
    return Intrinsics(intrinsics.id, new_model, intrinsics.width, intrinsics.height,
                      np.asarray(new_params, dtype=np.float64), intrinsics.prior_focal)


def pycolmap_camera(intrinsics: Intrinsics, camera_id: int | None = None):
    pycolmap = import_pycolmap()
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


def to_openmvg_scene(scene: SfMScene, camera_id_shift: int = 0) -> SfMScene:
    """A copy of ``scene`` whose intrinsics are OpenMVG models (for ``io.openmvg`` writers).

    COLMAP cameras with an exact OpenMVG equivalent keep their keypoints. The others
    (fx != fy, models OpenMVG lacks) become an undistorted ``pinhole`` with
    f = (fx + fy) / 2 and the same principal point, and their keypoints (and stored
    landmark pixels) are re-rendered from ``normalized`` through it, so normalized
    coordinates — what rotonly uses — are unchanged: the same rays, nothing lost.
    ``camera_id_shift``: added to a camera's id where the debug line names it (the id
    the user knows when ``scene``'s ids were shifted, :func:`colmap_to_openmvg`).
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
            camera = pycolmap_camera(intrinsic)
            focal = float(np.mean([camera.focal_length_x, camera.focal_length_y]))
            exact = Intrinsics(intrinsic_id, "pinhole", intrinsic.width, intrinsic.height,
                               np.array([focal, camera.principal_point_x,
                                         camera.principal_point_y]))
            resampled[intrinsic_id] = exact
            logger.debug("camera %d (%s) in sfm_data.json: OpenMVG's pinhole f=%.6g, its keypoints placed for it "
                         "(the same rays; OpenMVG has no model of this camera's parameters)",
                         intrinsic_id + camera_id_shift, intrinsic.model, focal)
            logger.debug("camera %d params %s", intrinsic_id + camera_id_shift,
                         np.array2string(params, precision=6))
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
    camera_shift = down(scene.intrinsics)
    shifted = shift_ids(scene, down(scene.views), camera_shift, down(point_ids))
    return to_openmvg_scene(shifted, camera_id_shift=-camera_shift)


def normalize_keypoints(camera, keypoints: np.ndarray) -> np.ndarray:
    """(n, 2) COLMAP-convention pixels -> (n, 2) undistorted normalized coordinates, one
    batched ``Camera.cam_from_img`` call (pycolmap's own undistortion)."""
    keypoints = np.ascontiguousarray(keypoints, dtype=np.float64).reshape(-1, 2)
    if keypoints.shape[0] == 0:
        return np.zeros((0, 2))
    return np.asarray(camera.cam_from_img(keypoints), dtype=np.float64)
