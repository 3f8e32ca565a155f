"""Which cameras to calibrate (calibration/, step 1): the cameras the input leaves out or marks
as a guess, the ones whose reprojection errors or centred principal point show them wrong, and
the twins (cameras given identical intrinsics: one device) calibrated as one.

COLMAP marks a focal it guessed (1.2 x the image size) with ``prior_focal_length = 0``;
OpenMVG marks nothing, so there the data decides after a first reconstruction
(:func:`suspect_cameras`: a mean reprojection error well above calibrated cameras', confirmed
by one adjustment; :func:`centred_principal_point`: a principal point left at the image
centre, the front ends' default, checked by one adjustment)."""

from __future__ import annotations

import copy
import logging
from dataclasses import replace

import numpy as np

from rotonly_cli.io import cameras
from rotonly_cli.options import Intrinsics as Mode
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import Intrinsics, SfMScene

logger = logging.getLogger(__name__)

def guess_missing_cameras(scene: SfMScene, mode: Mode, openmvg: bool) -> tuple[SfMScene, list[int]]:
    """``scene`` (not changed) with a camera for the views that have keypoints but no camera in
    the input, and those view ids. OpenMVG's image listing leaves a view's intrinsic undefined
    when the image has no EXIF focal, or one from a camera its sensor database does not know,
    and neither ``-f`` nor ``-k`` was given; OpenMVG's SfM cannot use such a view. Here the
    views of one image size share a camera with COLMAP's guess (io.cameras.guessed_intrinsics:
    f = 1.2 x the larger side, marked as a guess; the principal point of the given cameras of
    that size, if any: :func:`_principal_point_of_size`), which ``auto`` and ``refine``
    calibrate: what the listing's ``-f`` would have made of them (it groups views of one size
    and focal into one intrinsic). One camera per view, as COLMAP's front end makes them,
    measured worse (docs/tuning.md "Intrinsics"). ``fixed`` calibrates nothing: there the
    views stay without a camera and out of the outputs (the run warns)."""
    missing = [v for v, view in sorted(scene.views.items())
               if view.intrinsics_id not in scene.intrinsics and v in scene.keypoints]
    if mode == Mode.FIXED or not missing:
        return scene, []
    guesses, camera_of_view = cameras.guessed_cameras_per_size([scene.views[v] for v in missing],
                                                               max(scene.intrinsics, default=-1) + 1, openmvg)
    out = copy.copy(scene)
    out.views, out.normalized = dict(scene.views), dict(scene.normalized)
    out.intrinsics = {**scene.intrinsics, **{c: _principal_point_of_size(k, scene) for c, k in guesses.items()}}
    for view_id, camera_id in camera_of_view.items():
        out.views[view_id] = replace(scene.views[view_id], intrinsics_id=camera_id)
        out.normalized[view_id] = cameras.normalize(out.intrinsics[camera_id], scene.keypoints[view_id])
    logger.info("intrinsics: %d view(s) without a camera in the input (no EXIF focal): %d camera(s), one per image "
                "size, with COLMAP's guess f = %.1f x the larger side, to calibrate", len(missing), len(guesses),
                cameras.GUESS_FOCAL_FACTOR)
    return out, missing


def _principal_point_of_size(guess: Intrinsics, scene: SfMScene) -> Intrinsics:
    """``guess`` with the principal point of the views of ``scene`` whose camera is given and
    of the guess's image size (their median), if there are any. Such views' images most likely
    come from the device whose other images kept their EXIF (an edit or a messenger strips
    it), and a principal point that a few images see cannot be estimated (to first order it is
    a rotation of the camera: ``min_images_principal_point``); the image centre is 10 px off
    on real cameras, and costs accuracy (docs/tuning.md "Measurements behind the code").
    Where the listing left the given cameras at the centre, nothing changes."""
    of_views = [scene.intrinsics[view.intrinsics_id] for view in scene.views.values()
                if view.intrinsics_id in scene.intrinsics]
    given = [np.asarray(k.params, dtype=np.float64)[cameras.parameter_groups(k)["principal_point"]]
             for k in of_views if (k.width, k.height) == (guess.width, guess.height)]
    if not given:
        return guess
    params = np.array(guess.params, dtype=np.float64)
    params[cameras.parameter_groups(guess)["principal_point"]] = np.median(given, axis=0)
    return replace(guess, params=params)


def cameras_to_calibrate(scene: SfMScene, mode: Mode) -> set[int]:
    """Cameras whose intrinsics are calibrated from the start: every camera (refine), the
    ones the input marks as a guess (auto), none (fixed)."""
    if mode == Mode.REFINE:
        return set(scene.intrinsics)
    if mode == Mode.AUTO:
        return {camera_id for camera_id, intrinsic in scene.intrinsics.items() if intrinsic.prior_focal is False}
    return set()


def reprojection_errors(scene: SfMScene) -> dict[int, np.ndarray]:
    """Per camera the reprojection errors (px) of every observation of the posed ``scene``'s
    points, through the camera model with its distortion."""
    structure = scene.structure
    if structure is None or not len(structure.points):
        return {}
    track_lengths, view_feature = structure.flat_observations()
    points = np.repeat(np.asarray(structure.points, dtype=np.float64), track_lengths, axis=0)
    errors: dict[int, list[np.ndarray]] = {}
    order = np.argsort(view_feature[:, 0], kind="stable")
    views, starts = np.unique(view_feature[order, 0], return_index=True)
    for view_id, rows in zip(views.tolist(), np.split(order, starts[1:])):
        pose = scene.poses[view_id]
        intrinsic = scene.intrinsics[scene.views[view_id].intrinsics_id]
        in_camera = (points[rows] - pose.center) @ np.asarray(pose.R_cam_from_world).T
        pixels = cameras.project(intrinsic, in_camera[:, :2] / in_camera[:, 2:3])
        observed = np.asarray(scene.keypoints[view_id], dtype=np.float64)[view_feature[rows, 1]]
        errors.setdefault(intrinsic.id, []).append(np.linalg.norm(pixels - observed, axis=1))
    return {camera_id: np.concatenate(blocks) for camera_id, blocks in errors.items()}


def mean_reprojection_errors(scene: SfMScene) -> tuple[dict[int, float], float | None]:
    """(per camera mean reprojection error in px, the mean over every observation)."""
    errors = reprojection_errors(scene)
    if not errors:
        return {}, None
    overall = np.concatenate(list(errors.values()))
    return {camera_id: float(e.mean()) for camera_id, e in errors.items()}, float(overall.mean())


def suspect_threshold_px(noise_sigma_px: float | None, options: IntrinsicsOptions) -> float:
    """The reprojection error sigma above which a camera's intrinsics are wrong: well above
    the matches' noise (:func:`projective_noise_sigma_px`), and never below
    ``suspect_reprojection_px``."""
    floor = options.suspect_reprojection_px
    return floor if noise_sigma_px is None else max(floor, options.suspect_noise_sigmas * noise_sigma_px)



def centred_principal_point(intrinsics: Intrinsics, tolerance_px: float) -> bool:
    """Whether the camera's principal point lies within ``tolerance_px`` of the image centre
    on both axes: what COLMAP's feature extractor and OpenMVG's image listing write when they
    do not know it (COLMAP's convention: (w/2, h/2); OpenMVG's w/2 is half a pixel further)."""
    index = cameras.parameter_groups(intrinsics)["principal_point"]
    if index.size != 2:
        return False
    offset = np.asarray(intrinsics.params, dtype=np.float64)[index] - 0.5 * np.array([intrinsics.width,
                                                                                       intrinsics.height])
    return bool(np.all(np.abs(offset) <= tolerance_px + 1e-9))


def suspect_cameras(per_camera_px: dict[int, float], threshold_px: float) -> set[int]:
    """Cameras whose mean reprojection error shows their intrinsics wrong."""
    return {camera_id for camera_id, error in per_camera_px.items() if error > threshold_px}


def twin_cameras(intrinsics: dict[int, Intrinsics], camera_ids) -> list[list[int]]:
    """``camera_ids`` grouped by identical intrinsics as given (model, size, parameters and
    whether the focal is a guess): what COLMAP's front end makes of one device when it
    gives every image its own camera (its default), each group sorted."""
    groups: dict[tuple, list[int]] = {}
    for camera_id in sorted(camera_ids):
        k = intrinsics[camera_id]
        key = (k.model, int(k.width), int(k.height), tuple(np.asarray(k.params, dtype=np.float64).ravel().tolist()),
               k.prior_focal)
        groups.setdefault(key, []).append(camera_id)
    return list(groups.values())




def merged_twins(subset: SfMScene, groups: list[list[int]]) -> SfMScene:
    """``subset`` with the cameras of each group as one camera (the group's first, with the
    median of the group's focal lengths), which all the group's views use."""
    intrinsics, owner = dict(subset.intrinsics), {}
    for group in groups:
        first = intrinsics[group[0]]
        focal = cameras.parameter_groups(first)["focal"]
        params = np.array(first.params, dtype=np.float64)
        params[focal] = np.median([np.asarray(intrinsics[c].params, dtype=np.float64)[focal] for c in group], axis=0)
        intrinsics[group[0]] = replace(first, params=params)
        for camera_id in group[1:]:
            del intrinsics[camera_id]
            owner[camera_id] = group[0]
    views = {v: replace(view, intrinsics_id=owner.get(view.intrinsics_id, view.intrinsics_id))
             for v, view in subset.views.items()}
    return replace(subset, intrinsics=intrinsics, views=views)


