"""Camera models of either source tool behind one interface: pixels <-> normalized coordinates
with the source tool's own model, and the COLMAP model that stands in for an intrinsic when
pycolmap refines it (calibration/).

OpenMVG intrinsics (lower-case model names) use OpenMVG's formulas (io/openmvg/cameras.py),
COLMAP cameras pycolmap's. Pixels are in COLMAP's convention everywhere (scene/types.py).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.colmap.cameras import normalize_keypoints, pycolmap_camera, to_colmap_intrinsics
from rotonly_cli.io.openmvg.cameras import distort_project, undistort_normalize
from rotonly_cli.scene.types import Intrinsics, SfMScene, View

#: OpenMVG model <-> the COLMAP model with the same parameters in the same order
#: (formats.md §4.4); ``pinhole_radial_k3`` only while k3 = 0 (then it is COLMAP's RADIAL)
_SAME_PARAMETERS = {"pinhole": "SIMPLE_PINHOLE", "pinhole_radial_k1": "SIMPLE_RADIAL"}
#: models without a radial term -> the model that adds one (k1 = 0 reproduces the original)
_WITH_RADIAL = {"SIMPLE_PINHOLE": "SIMPLE_RADIAL", "pinhole": "pinhole_radial_k1"}


#: COLMAP's focal for an image without EXIF focal: this x the larger image side
#: (ImageReaderOptions.default_focal_length_factor; formats.md §4.4)
GUESS_FOCAL_FACTOR = 1.2


def guessed_intrinsics(camera_id: int, width: int, height: int, openmvg: bool) -> Intrinsics:
    """The camera COLMAP's front end gives an image without EXIF focal: SIMPLE_RADIAL with
    f = GUESS_FOCAL_FACTOR x the larger side, the principal point at the centre and k = 0,
    marked as a guess (``prior_focal`` False); ``openmvg``: as OpenMVG's
    ``pinhole_radial_k1``, the same parameters in the same order."""
    if width <= 0 or height <= 0:
        raise InputError("a camera to guess needs the image size", field=f"camera {camera_id}")
    return Intrinsics(camera_id, "pinhole_radial_k1" if openmvg else "SIMPLE_RADIAL", int(width), int(height),
                      np.array([GUESS_FOCAL_FACTOR * max(width, height), width / 2, height / 2, 0.0]),
                      prior_focal=False)


def guessed_cameras_per_size(views: list[View], first_id: int,
                             openmvg: bool) -> tuple[dict[int, Intrinsics], dict[int, int]]:
    """For ``views`` that have no camera: one :func:`guessed_intrinsics` per image size, ids
    from ``first_id`` up in the order of the views, and {view id: its camera id}. A view
    without its size cannot be guessed (InputError)."""
    guesses: dict[int, Intrinsics] = {}
    camera_of_size: dict[tuple[int, int], int] = {}
    camera_of_view: dict[int, int] = {}
    for view in views:
        if not view.width or not view.height:
            raise InputError("a view without intrinsic needs its image size (width, height) for a guessed camera",
                             field=f"views[{view.id}]")
        size = (int(view.width), int(view.height))
        if size not in camera_of_size:
            camera_of_size[size] = camera_id = first_id + len(camera_of_size)
            guesses[camera_id] = guessed_intrinsics(camera_id, *size, openmvg)
        camera_of_view[view.id] = camera_of_size[size]
    return guesses, camera_of_view


def is_openmvg_model(intrinsics: Intrinsics) -> bool:
    return intrinsics.model.islower()


def normalize(intrinsics: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(n, 2) pixels -> (n, 2) undistorted normalized coordinates (z = 1), with the source
    tool's own undistortion (what the readers do)."""
    if is_openmvg_model(intrinsics):
        return undistort_normalize(intrinsics, pixels)
    return normalize_keypoints(pycolmap_camera(intrinsics), pixels)


def project(intrinsics: Intrinsics, normalized: np.ndarray) -> np.ndarray:
    """(n, 2) undistorted normalized coordinates -> (n, 2) pixels (distortion added)."""
    normalized = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
    if is_openmvg_model(intrinsics):
        return distort_project(intrinsics, normalized)
    if normalized.shape[0] == 0:
        return np.zeros((0, 2))
    camera = pycolmap_camera(intrinsics)
    rays = np.column_stack([normalized, np.ones(len(normalized))])
    return np.asarray(camera.img_from_cam(rays), dtype=np.float64).reshape(-1, 2)


#: a keypoint whose normalized coordinates map back through the camera model farther than this
#: (pixels) from where it was found was not undistorted: the model's inverse failed there
UNDISTORTION_TOLERANCE_PX = 0.5


def undistortion_failures(intrinsics: Intrinsics, pixels: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """(n,) bool: the keypoints whose ``normalized`` coordinates are not the model's inverse of
    ``pixels`` (non-finite, or projecting back more than UNDISTORTION_TOLERANCE_PX away). A ray
    90° or more off the optical axis (a fisheye wider than 180°) has no z = 1 coordinates at
    all; pycolmap then returns the distorted coordinates unchanged."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    normalized = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
    finite = np.all(np.isfinite(normalized), axis=1)
    failed = ~finite
    if finite.any():
        back = project(intrinsics, normalized[finite])
        failed[finite] = ~(np.linalg.norm(back - pixels[finite], axis=1) <= UNDISTORTION_TOLERANCE_PX)
    return failed


def undistorted_pixels(intrinsics: Intrinsics, normalized: np.ndarray) -> np.ndarray:
    """(n, 2) undistorted normalized coordinates -> (n, 2) pixels of the same camera without its
    distortion (focal length(s) and principal point only)."""
    groups = parameter_groups(intrinsics)
    params = np.asarray(intrinsics.params, dtype=np.float64)
    focal = params[groups["focal"]]
    return np.asarray(normalized, dtype=np.float64).reshape(-1, 2) * (focal if focal.size == 2 else focal[0]) \
        + params[groups["principal_point"]]


def renormalize(scene: SfMScene, intrinsics: dict[int, Intrinsics]) -> None:
    """Replace ``scene``'s intrinsics by ``intrinsics`` (by id) and recompute the normalized
    coordinates of every view that uses one of them, in place."""
    for intrinsic_id, intrinsic in intrinsics.items():
        scene.intrinsics[intrinsic_id] = intrinsic
    for view_id, view in scene.views.items():
        if view.intrinsics_id in intrinsics and view_id in scene.keypoints:
            scene.normalized[view_id] = normalize(intrinsics[view.intrinsics_id], scene.keypoints[view_id])


# ============================================================================ refinement model

def refinement_model(intrinsics: Intrinsics) -> Intrinsics | None:
    """The COLMAP camera whose parameters pycolmap's bundle adjuster refines in place of
    ``intrinsics``: its own COLMAP model, with a radial term added to models without one
    (SIMPLE_PINHOLE, OpenMVG ``pinhole``: k1 = 0 projects the same). None for OpenMVG models
    whose COLMAP counterpart has two focal lengths or other terms OpenMVG cannot hold
    (``pinhole_radial_k3`` with k3 != 0, ``pinhole_brown_t2``, ``fisheye``)."""
    params = np.asarray(intrinsics.params, dtype=np.float64).ravel()
    model = intrinsics.model
    if is_openmvg_model(intrinsics):
        if model == "pinhole_radial_k3" and params.size == 6 and params[5] == 0.0:
            return replace(intrinsics, model="RADIAL", params=params[:5].copy())
        if model not in _SAME_PARAMETERS:
            return None
        intrinsics = replace(intrinsics, model=_SAME_PARAMETERS[model], params=params.copy())
        model = intrinsics.model
    if model in _WITH_RADIAL:
        return replace(intrinsics, model=_WITH_RADIAL[model], params=np.append(params, 0.0))
    pycolmap_camera(intrinsics)  # validates a COLMAP model name / parameter count
    return replace(intrinsics, params=params.copy())


def from_refinement_model(original: Intrinsics, refined: Intrinsics) -> Intrinsics:
    """``refined`` (a :func:`refinement_model` camera with new parameters) in the source
    tool's terms: the original model, or the model with a radial term when the refinement
    added one and kept a non-zero coefficient."""
    params = np.asarray(refined.params, dtype=np.float64).ravel()
    added = original.model in _WITH_RADIAL
    if added and params[-1] == 0.0:  # the added radial term stayed zero: the original model
        return replace(original, params=params[:-1].copy())
    if not is_openmvg_model(original):
        return replace(original, model=refined.model, params=params.copy())
    if original.model == "pinhole_radial_k3":
        return replace(original, params=np.append(params, 0.0))
    model = _WITH_RADIAL[original.model] if added else original.model
    return replace(original, model=model, params=params.copy())


def parameter_groups(intrinsics: Intrinsics) -> dict[str, np.ndarray]:
    """Indices of the focal length(s), the principal point and the distortion terms in the
    parameters of a COLMAP or OpenMVG model."""
    camera = pycolmap_camera(to_colmap_intrinsics(intrinsics))
    if is_openmvg_model(intrinsics):  # f, cx, cy, distortion...
        size = np.asarray(intrinsics.params).size
        return {"focal": np.array([0]), "principal_point": np.array([1, 2]), "distortion": np.arange(3, size)}
    return {"focal": np.asarray(camera.focal_length_idxs(), dtype=np.int64),
            "principal_point": np.asarray(camera.principal_point_idxs(), dtype=np.int64),
            "distortion": np.asarray(camera.extra_params_idxs(), dtype=np.int64)}
