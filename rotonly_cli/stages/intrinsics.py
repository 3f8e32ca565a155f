"""Stage `intrinsics`: cameras as users have them (guessed focal lengths, unknown distortion).

rotonly's rotation stages work on normalized coordinates, so they are only as good as the
intrinsics that make them. This module holds the pieces that ``chain.py`` chains around
the other stages (``--intrinsics auto|refine``; docs/algorithms.md §8):

1. **Which cameras are guesses** (:func:`cameras_to_calibrate`): COLMAP marks a focal it
   guessed (1.2 x the image size) with ``prior_focal_length = 0``; OpenMVG marks nothing,
   so there the data decides after a first reconstruction (:func:`suspect_cameras`: a mean
   reprojection error well above calibrated cameras' 0.2 px, confirmed by one adjustment;
   :meth:`Calibration.check_centred`: a principal point left at the image centre, the front
   ends' default, checked by one adjustment).
2. **Focal lengths from the view graph** (:func:`view_graph_focals`), before any rotation is
   estimated: F re-fitted on every verified pair's matches, then
   ``pycolmap.calibrate_view_graph`` — COLMAP's port of GLOMAP's ViewGraphCalibrator
   (Fetzer et al., WACV 2020), not a copy of it — on a private database in a temporary
   folder. The load stage then re-estimates every relative pose with a calibrated E.
3. **Intrinsics from the reconstruction** (:func:`estimate_intrinsics`): once rotonly has
   rotations, centres and points, pycolmap's bundle adjuster estimates focal, principal
   point and radial terms on the longest tracks (one principal point per set of cameras
   given the same intrinsics, :func:`twin_cameras`, where at least two images see it). It
   moves poses and points too (with them held, K barely moves: docs/tuning.md
   "Intrinsics"), but it serves **only as an intrinsics estimator**: its poses and points
   are discarded, and the pipeline runs rotonly's own stages again on keypoints normalized
   with the new intrinsics. The poses rotonly writes are always the product of its
   rotation-only stages.
4. **Only significant changes** (:func:`gate`): a change of the focal, the principal point
   or the distortion is kept when it moves some pixel of the image by more than
   ``min_shift`` of its half diagonal; refining parameters that were right costs accuracy.
"""

from __future__ import annotations

import copy
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import cameras
from rotonly_cli.io.colmap import id_offset
from rotonly_cli.io.colmap.database import read_camera_params, write_fundamental_database
from rotonly_cli.io.colmap.model import model_reconstruction
from rotonly_cli.options import Intrinsics as Mode
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.runtime.parallel import edge_parts, fork_map
from rotonly_cli.scene.types import Intrinsics, SfMScene

logger = logging.getLogger(__name__)

#: two-view configurations whose matches do not constrain a fundamental matrix (a plane or a
#: pure rotation: the homography's F family is degenerate), left out of the calibration
_NO_FUNDAMENTAL = ("PLANAR", "PLANAR_OR_PANORAMIC", "PANORAMIC", "H", "DEGENERATE", "UNDEFINED", "WATERMARK")
GROUPS = ("focal", "principal_point", "distortion")


def half_diagonal(intrinsics: Intrinsics) -> float:
    return 0.5 * float(np.hypot(intrinsics.width, intrinsics.height))


def describe(intrinsics: Intrinsics) -> dict:
    """JSON form of a camera for the reports."""
    return {"model": intrinsics.model, "width": int(intrinsics.width), "height": int(intrinsics.height),
            "params": [float(v) for v in np.asarray(intrinsics.params, dtype=float).ravel()],
            "focal_px": intrinsics.focal_px}


# ============================================================================ 1. which cameras

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
    measured worse on Strecha's OpenMVG projects with every intrinsic removed (castle-P19 0.30
    against 0.10 deg; docs/tuning.md "Intrinsics"). ``fixed`` calibrates nothing: there the
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
    a rotation of the camera: ``min_images_principal_point``): Herz-Jesus-P8's and entry-P10's
    OpenMVG projects with one view's intrinsic undefined ended at 0.105 and 0.056-0.128 deg
    with the guess's centre, 10 px off, and at 0.040 and 0.023-0.033 deg with it (all given:
    0.040 and 0.022 deg). Where the listing left the given cameras at the centre, nothing changes."""
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


#: the noise sigma needs this many inlier residuals to be trusted
MIN_NOISE_SAMPLES = 50


def projective_noise_sigma_px(scene: SfMScene, options: IntrinsicsOptions) -> float | None:
    """Noise sigma (px) of the matches whatever the focal lengths: 1.4826 x the median Sampson
    distance to a fundamental matrix fitted (LO-RANSAC, ``fundamental_max_error_px``) on each
    of the ``noise_sample_pairs`` largest verified pairs. The load stage's sigma comes from
    essential matrices, which wrong intrinsics inflate as much as the reprojection errors
    (a focal 10 % off with k1 = -0.3: 1.1 px against 0.5 px). Where too few pairs hold a
    fundamental matrix (a flat ground seen from above, a panorama: their pairs are PLANAR or
    PANORAMIC), the homographies of those pairs give it instead, as free of the intrinsics
    (:func:`homography_noise_sigma_px`). None with too few inliers."""
    import pycolmap

    from rotonly_cli.geometry.pairwise import epipolar_sampson_errors

    ransac = pycolmap.RANSACOptions(max_error=options.fundamental_max_error_px, random_seed=options.seed,
                                    min_num_trials=options.fundamental_min_trials)
    errors = [np.zeros(0)]
    for pair in _noise_sample(scene, lambda config: config not in _NO_FUNDAMENTAL, options):
        x_i, x_j = _undistorted_pair_pixels(scene, pair)
        result = pycolmap.estimate_fundamental_matrix(x_i, x_j, ransac)
        if result is not None:
            inliers = np.asarray(result["inlier_mask"], dtype=bool).ravel()
            errors.append(epipolar_sampson_errors(result["F"], x_i[inliers], x_j[inliers]))
    errors = np.concatenate(errors)
    if errors.size >= MIN_NOISE_SAMPLES:
        return 1.4826 * float(np.median(errors))
    return homography_noise_sigma_px(scene, options)


#: two-view configurations a homography explains (COLMAP's names; "H": OpenMVG's matches.h)
_HOMOGRAPHY_CONFIGS = ("PLANAR", "PLANAR_OR_PANORAMIC", "PANORAMIC", "H")


def homography_noise_sigma_px(scene: SfMScene, options: IntrinsicsOptions) -> float | None:
    """Noise sigma (px) of the matches from homographies fitted on the ``noise_sample_pairs``
    largest verified pairs a homography explains (LO-RANSAC, then least squares on its
    inliers; inliers: transfer error within ``fundamental_max_error_px``): median / √(2 ln 2)
    of the inliers' first-order distances (two constraints per match,
    geometry.pairwise.homography_transfer_errors). None with too few inliers."""
    import cv2
    import pycolmap

    from rotonly_cli.geometry.pairwise import homography_transfer_errors

    ransac = pycolmap.RANSACOptions(max_error=options.fundamental_max_error_px, random_seed=options.seed,
                                    min_num_trials=options.fundamental_min_trials)
    errors = [np.zeros(0)]
    for pair in _noise_sample(scene, lambda config: config in _HOMOGRAPHY_CONFIGS, options):
        x_i, x_j = _undistorted_pair_pixels(scene, pair)
        result = pycolmap.estimate_homography_matrix(x_i, x_j, ransac)
        if result is None:
            continue
        # LO-RANSAC stops early on these verified matches, and its H can sit far enough from
        # the inliers' optimum to inflate sigma by a third (flat ground seen from above): the
        # least-squares H of its inliers, and the matches within the threshold of that
        inliers = np.asarray(result["inlier_mask"], dtype=bool).ravel()
        H = result["H"]
        if inliers.sum() >= 8:
            H, _ = cv2.findHomography(x_i[inliers], x_j[inliers], 0)
        if H is None:
            continue
        mapped = np.column_stack([x_i, np.ones(len(x_i))]) @ H.T
        inliers = np.linalg.norm(x_j - mapped[:, :2] / mapped[:, 2:3], axis=1) <= options.fundamental_max_error_px
        errors.append(homography_transfer_errors(H, x_i[inliers], x_j[inliers]))
    errors = np.concatenate(errors)
    return float(np.median(errors)) / np.sqrt(2.0 * np.log(2.0)) if errors.size >= MIN_NOISE_SAMPLES else None


def _noise_sample(scene: SfMScene, takes_config: Callable[[str | None], bool], options: IntrinsicsOptions) -> list:
    """The ``noise_sample_pairs`` largest verified pairs (8 matches or more) whose
    configuration ``takes_config`` accepts."""
    usable = [pair for pair in scene.pairs.values() if pair.verified and takes_config(pair.config)
              and pair.i in scene.normalized and pair.j in scene.normalized and len(pair.matches) >= 8]
    return sorted(usable, key=lambda p: (-len(p.matches), p.i, p.j))[:options.noise_sample_pairs]


def _undistorted_pair_pixels(scene: SfMScene, pair) -> tuple[np.ndarray, np.ndarray]:
    """A pair's matched keypoints as undistorted pixels of their cameras."""
    matches = np.asarray(pair.matches, dtype=np.int64)
    return tuple(np.ascontiguousarray(cameras.undistorted_pixels(
        scene.intrinsics[scene.views[v].intrinsics_id], scene.normalized[v][matches[:, column]]))
        for v, column in ((pair.i, 0), (pair.j, 1)))


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


# ============================================================================ 2. view-graph calibration

#: the F re-fit forks a process per this many matches at most (a fork costs ~30 ms)
MIN_MATCHES_PER_PROCESS = 20_000


def refit_fundamentals(scene: SfMScene, options: IntrinsicsOptions, jobs: int = 1) -> dict[tuple[int, int], np.ndarray]:
    """F of every verified pair that can hold one, from pycolmap's LO-RANSAC with Sampson
    refinement on the pair's matches, in pixels without the cameras' known distortion (the
    keypoints themselves when there is none). COLMAP 3.8 stores F without that refinement:
    the view-graph focal of fountain-P11's guessed database was 2.4 % off with the stored F,
    0.03 % with the re-fitted one (docs/tuning.md). ``jobs``: processes (forked)."""
    import pycolmap

    ransac = pycolmap.RANSACOptions(max_error=options.fundamental_max_error_px, random_seed=options.seed,
                                    min_num_trials=options.fundamental_min_trials)
    pixels = {view_id: cameras.undistorted_pixels(scene.intrinsics[view.intrinsics_id], scene.normalized[view_id])
              for view_id, view in scene.views.items() if view_id in scene.normalized}
    keys = [key for key, pair in sorted(scene.pairs.items()) if pair.verified and pair.config not in _NO_FUNDAMENTAL
            and len(pair.matches) >= 8 and key[0] in pixels and key[1] in pixels]

    def fit(part: tuple[int, int]) -> dict[tuple[int, int], np.ndarray]:
        fitted = {}
        for i, j in keys[part[0]:part[1]]:
            matches = np.asarray(scene.pairs[(i, j)].matches, dtype=np.int64)
            result = pycolmap.estimate_fundamental_matrix(np.ascontiguousarray(pixels[i][matches[:, 0]]),
                                                          np.ascontiguousarray(pixels[j][matches[:, 1]]), ransac)
            if result is not None:
                fitted[(i, j)] = np.asarray(result["F"], dtype=np.float64)
        return fitted

    # pycolmap holds the GIL here: processes, not threads (each fit is seeded: same result)
    counts = np.array([len(scene.pairs[key].matches) for key in keys], dtype=np.int64)
    parts = edge_parts(counts, jobs, MIN_MATCHES_PER_PROCESS) if jobs > 1 and keys else [(0, len(keys))]
    fundamentals: dict[tuple[int, int], np.ndarray] = {}
    for fitted in fork_map(fit, parts):
        fundamentals.update(fitted)
    return dict(sorted(fundamentals.items()))


def view_graph_focals(scene: SfMScene, calibrate: set[int], options: IntrinsicsOptions,
                      jobs: int = 1) -> tuple[dict[int, Intrinsics], dict]:
    """New intrinsics (only the focal length changed) of the cameras in ``calibrate``, by
    ``pycolmap.calibrate_view_graph`` over the re-fitted fundamental matrices; the other
    cameras are held constant. Cameras given identical intrinsics (:func:`twin_cameras`:
    COLMAP's camera per image) are calibrated as one, as in the first adjustment of a round:
    entry-P10's guessed database with a camera per image has 9 fundamental matrices for 10
    cameras, and a focal each put cameras 1 and 2 at 574 and 476 px (true 1381), which took
    four rounds (22 s) to undo. Twins whose focal the input gives (an EXIF camera per image,
    calibrated as suspects) share it too: a focal each left entry-P10's such database at
    0.1638 deg (shared: 0.0460), though castle-P19's gained by it (0.038 against 0.044 deg,
    seeds 0-2)."""
    start = time.perf_counter()
    fundamentals = refit_fundamentals(scene, options, jobs)
    report = {"cameras": sorted(calibrate), "num_pairs": len(fundamentals), "refit_time_s": time.perf_counter() - start}
    if len(fundamentals) < options.min_fundamental_pairs:
        report.update(success=False, time_s=time.perf_counter() - start)
        if fundamentals:
            logger.info("intrinsics: view-graph calibration skipped: %d pair(s) with a fundamental matrix (< %d)",
                        len(fundamentals), options.min_fundamental_pairs)
        return {}, report
    groups = [group for group in twin_cameras(scene.intrinsics, calibrate) if len(group) > 1]
    owner = {camera_id: group[0] for group in groups for camera_id in group}
    merged = _merged(scene, groups) if groups else scene
    success, params = _calibrate_view_graph(merged, fundamentals, {owner.get(c, c) for c in calibrate}, options)
    calibrated = {}
    for camera_id in sorted(calibrate):
        given = scene.intrinsics[camera_id]
        colmap_given = cameras.to_colmap_intrinsics(given)
        focal_idx = cameras.parameter_groups(colmap_given)["focal"]
        new_focals = params[owner.get(camera_id, camera_id)][focal_idx]
        focal = float(np.mean(new_focals))
        if not (success and np.isfinite(focal) and focal > 0) or np.allclose(new_focals, np.asarray(
                colmap_given.params)[focal_idx]):
            continue  # not calibrated (too few usable pairs): stays as given
        updated = np.array(given.params, dtype=np.float64)
        updated[cameras.parameter_groups(given)["focal"]] = focal
        calibrated[camera_id] = replace(given, params=updated)
    report.update(success=success, focal_px={str(c): k.focal_px for c, k in calibrated.items()},
                  time_s=time.perf_counter() - start)
    logger.info("intrinsics: view-graph calibration over %d pairs: %s (%.2f s)", len(fundamentals),
                ", ".join(f"camera {c} f {scene.intrinsics[c].focal_px:.1f} -> {k.focal_px:.1f} px"
                          for c, k in calibrated.items()) or "no camera calibrated", report["time_s"])
    return calibrated, report


def _calibrate_view_graph(scene: SfMScene, fundamentals: dict[tuple[int, int], np.ndarray], free: set[int],
                          options: IntrinsicsOptions) -> tuple[bool, dict[int, np.ndarray]]:
    """``pycolmap.calibrate_view_graph`` of ``scene``'s cameras in ``free`` (the others held)
    over ``fundamentals``, on a database written for it in a temporary folder (removed on
    every exit path: it rewrites the database it is given): (success, {camera: params in
    COLMAP's model order})."""
    import pycolmap

    with tempfile.TemporaryDirectory(prefix="rotonly-vgc-") as scratch:
        path = Path(scratch) / "database.db"
        write_fundamental_database(path, scene, fundamentals, free)
        calibration = pycolmap.ViewGraphCalibrationOptions(random_seed=options.seed, reestimate_relative_pose=False)
        success = bool(pycolmap.calibrate_view_graph(str(path), calibration))
        return success, read_camera_params(path, scene)


def per_image_focals(scene: SfMScene, devices: list[list[int]], fundamentals: dict[tuple[int, int], np.ndarray],
                     options: IntrinsicsOptions) -> dict:
    """Do the images of one camera agree on its focal length? For every device of ``devices``
    (a camera, or twins: :func:`twin_cameras`, as lists of camera ids), each of its images with at least
    ``zoom_min_pairs`` fundamental matrices gets a camera of its own, started at ``scene``'s
    focal, and the view graph is calibrated again with those free and the rest held; a
    device with at least ``zoom_min_images`` such images is checked by :func:`focal_groups`:
    {"focal_px": {camera: {view: focal}}, "disagree": [findings]}. A zoom lens or two devices
    under one camera (COLMAP's ``single_camera``, OpenMVG's ``-k``) give one focal to images
    taken at two: fountain-P11's database with four of its eleven images zoomed 5 % ended
    0.94 deg off, and no shared calibration fits both (docs/tuning.md "Intrinsics")."""
    paired, pairs_of = np.unique(np.array(list(fundamentals), dtype=np.int64).reshape(-1), return_counts=True)
    enough = set(paired[pairs_of >= options.zoom_min_pairs].tolist())
    checked = {}
    for group in devices:
        views = sorted(v for v, view in scene.views.items() if view.intrinsics_id in group and v in enough)
        if len(views) >= options.zoom_min_images:
            checked[group[0]] = views
    if not checked:
        return {}
    # every checked image its own camera (ids after the scene's), free
    own = {view_id: max(scene.intrinsics) + 1 + n for n, view_id in enumerate(v for vs in checked.values() for v in vs)}
    intrinsics = dict(scene.intrinsics)
    for view_id, camera_id in own.items():
        intrinsics[camera_id] = replace(scene.intrinsics[scene.views[view_id].intrinsics_id], id=camera_id)
    views = {v: replace(view, intrinsics_id=own.get(v, view.intrinsics_id)) for v, view in scene.views.items()}
    success, params = _calibrate_view_graph(replace(scene, intrinsics=intrinsics, views=views), fundamentals,
                                            set(own.values()), options)
    if not success:
        return {"success": False}
    focal_px, disagree = {}, []
    for first, views_ in checked.items():
        focal_idx = cameras.parameter_groups(cameras.to_colmap_intrinsics(scene.intrinsics[first]))["focal"]
        focal_px[first] = focals = {v: float(np.mean(params[own[v]][focal_idx])) for v in views_}
        groups = focal_groups(focals, options)
        if groups is not None:
            disagree.append({"camera": first, "groups": [{"views": group, "names": [scene.views[v].name for v in group],
                                                           "focal_px": float(np.median([focals[v] for v in group]))}
                                                          for group in groups]})
    return {"success": True, "focal_px": {str(c): {str(v): f for v, f in fs.items()} for c, fs in focal_px.items()},
            "disagree": disagree}


def focal_groups(focals: dict[int, float], options: IntrinsicsOptions) -> list[list[int]] | None:
    """The images of one camera split into two groups at the widest gap between their sorted
    focal lengths (``focals``: {view: px}) when that gap is a zoom's, not the calibration's
    scatter: at least ``zoom_min_gap`` (relative), ``zoom_gap_to_spread`` times the larger
    group's own range, and two images a side; None otherwise. Calibrated cameras' images
    scatter by ±0.5 % (Herz-Jesus-P8, fountain-P11) and, where few pairs hold a fundamental
    matrix, by tens of per cent with no gap between groups (entry-P10: -65 % to +0.2 %;
    castle-P19: -8 % to +3 %)."""
    views = [v for v, f in focals.items() if np.isfinite(f) and f > 0]
    if len(views) < 4:
        return None
    order = sorted(views, key=lambda v: focals[v])
    log_focal = np.log([focals[v] for v in order])
    gaps = np.diff(log_focal)
    cut = int(np.argmax(gaps)) + 1
    if cut < 2 or len(order) - cut < 2:
        return None
    spread = max(log_focal[cut - 1] - log_focal[0], log_focal[-1] - log_focal[cut])
    gap = float(gaps[cut - 1])
    if gap < np.log1p(options.zoom_min_gap) or gap < options.zoom_gap_to_spread * spread:
        return None
    return [sorted(order[:cut]), sorted(order[cut:])]


def zoom_warning(finding: dict, split_to: int | None = None, twins: bool = False) -> str:
    """The warning line of one :func:`focal_groups` finding of :func:`per_image_focals`;
    ``split_to``: the camera the calibration gave the images of one group (Calibration._split);
    ``twins``: the finding is about cameras given identical intrinsics (not split)."""
    low, high = finding["groups"]
    smaller = min((low, high), key=lambda g: len(g["views"]))
    other = high if smaller is low else low

    def names(group: dict, shown: int = 6) -> str:
        listed_ = ", ".join(group["names"][:shown])
        return listed_ + (f" and {len(group['names']) - shown} more" if len(group["names"]) > shown else "")

    found = (f"camera {finding['camera']}: its images disagree on the focal length: {len(smaller['views'])} "
             f"({names(smaller)}) at {smaller['focal_px']:.0f} px, {len(other['views'])} at {other['focal_px']:.0f} px "
             f"(the view-graph calibration with a camera per image): a zoom lens or two devices under one camera? ")
    if split_to is not None:
        return found + (f"The images of one focal were given camera {split_to} and both were calibrated (the outputs "
                        f"have it); with a camera per image (COLMAP: --ImageReader.single_camera 0; OpenMVG: "
                        f"SfMInit_ImageListing without -k) the input would say so itself")
    if twins:
        return found + ("One focal cannot fit both, and cameras given identical intrinsics are calibrated as one "
                        "device: give the images of each zoom their own intrinsics (their EXIF focal) and run again")
    return found + ("One focal cannot fit both: give each image its own camera (COLMAP: --ImageReader.single_camera 0; "
                    "OpenMVG: SfMInit_ImageListing without -k) and run again")


#: the input verifier's configurations of pairs a homography explains best: a rotating camera
#: (a panorama) has H = K R K⁻¹, which fixes the focal length where no F can (_NO_FUNDAMENTAL)
_ROTATION_CONFIGS = ("PANORAMIC", "PLANAR_OR_PANORAMIC")


def _at_most(rows: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``rows``, or a random subset of ``count`` of them in their order."""
    return rows if len(rows) <= count else rows[np.sort(rng.choice(len(rows), count, replace=False))]


def rotating_camera_focals(scene: SfMScene, calibrate: set[int],
                           options: IntrinsicsOptions) -> tuple[dict[int, Intrinsics], dict]:
    """New intrinsics (the focal length changed) of the cameras in ``calibrate`` whose pairs
    the input verified by a homography: the focal length at which those pairs' bearings are
    best explained by pure rotations (geometry.rotating_camera). Cameras with identical given
    intrinsics (:func:`twin_cameras`: COLMAP's camera per image) share one focal length and
    the pairs between their views. Kept when the search ends inside its range and the median
    of the pairs' median residuals is within ``options.rotation_fit_max_px``: a plane seen
    from two places fits no rotation at any focal length. For a capture of pure rotations,
    where the view-graph calibration has no fundamental matrix to work with (algorithms.md §8)."""
    from rotonly_cli.geometry.rotating_camera import rotating_camera_focal

    start = time.perf_counter()
    calibrated, fits = {}, {}
    for group in twin_cameras(scene.intrinsics, calibrate):
        given = scene.intrinsics[group[0]]
        on_group = {v for v, view in scene.views.items() if view.intrinsics_id in group and v in scene.normalized}
        keys = [key for key, pair in sorted(scene.pairs.items()) if pair.config in _ROTATION_CONFIGS
                and key[0] in on_group and key[1] in on_group and len(pair.matches) >= 8]
        if not keys:
            continue
        # undistorted pixel offsets from the principal point at the given focal length
        rng = np.random.default_rng(options.seed)
        matches = [_at_most(np.asarray(scene.pairs[key].matches).reshape(-1, 2), options.rotation_fit_max_matches, rng)
                   for key in keys]
        u_i = [scene.normalized[i][m[:, 0]] * given.focal_px for (i, _), m in zip(keys, matches)]
        u_j = [scene.normalized[j][m[:, 1]] * given.focal_px for (_, j), m in zip(keys, matches)]
        fit = rotating_camera_focal(u_i, u_j, given.focal_px)
        residual = float(np.median(fit.residual_px))
        kept = fit.interior and residual <= options.rotation_fit_max_px
        fits[",".join(map(str, group))] = {"cameras": group, "num_pairs": len(keys), "focal_px": fit.focal_px,
                                           "residual_px": residual, "kept": kept}
        if kept:
            params = np.array(given.params, dtype=np.float64)
            focal = cameras.parameter_groups(given)["focal"]
            params[focal] = params[focal] * (fit.focal_px / given.focal_px)
            for camera_id in group:
                calibrated[camera_id] = replace(scene.intrinsics[camera_id], params=params.copy())
    report = {"method": "rotating camera", "cameras": fits, "time_s": time.perf_counter() - start}
    if fits:
        logger.info("intrinsics: focal length of a rotating camera: %s (%.2f s)", ", ".join(
            f"camera(s) {c} f {scene.intrinsics[fit['cameras'][0]].focal_px:.1f} -> {fit['focal_px']:.1f} px over "
            f"{fit['num_pairs']} pure-rotation pairs, residual {fit['residual_px']:.2f} px"
            + ("" if fit["kept"] else " (not kept)") for c, fit in fits.items()), report["time_s"])
    return calibrated, report


# ============================================================================ 3. estimation from a reconstruction

def plausible(intrinsics: Intrinsics) -> bool:
    """Finite parameters, positive focal lengths, the principal point inside the image."""
    params = np.asarray(intrinsics.params, dtype=np.float64)
    groups = cameras.parameter_groups(intrinsics)
    cx, cy = params[groups["principal_point"]]
    return bool(np.all(np.isfinite(params)) and np.all(params[groups["focal"]] > 0)
                and 0 <= cx <= intrinsics.width and 0 <= cy <= intrinsics.height)


def longest_tracks(scene: SfMScene, max_points: int, seed: int = 0) -> SfMScene:
    """``scene`` with only its ``max_points`` longest tracks (ties broken at random, seeded)."""
    structure = scene.structure
    if structure is None or len(structure.points) <= max_points:
        return scene
    lengths, _ = structure.flat_observations()
    order = np.lexsort((np.random.default_rng(seed).random(len(lengths)), -lengths))[:max_points]
    keep = np.sort(order)
    subset = replace(structure, point_ids=np.asarray(structure.point_ids)[keep],
                     points=np.asarray(structure.points)[keep],
                     colors=None if structure.colors is None else np.asarray(structure.colors)[keep],
                     observations=[structure.observations[k] for k in keep.tolist()],
                     observation_pixels=None, observation_arrays=None)
    return replace(scene, structure=subset)


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


def _adjust(subset: SfMScene, refine: set[int], offset: int, options: IntrinsicsOptions, principal_point: bool):
    """pycolmap's bundle adjuster on the posed ``subset``: every pose and point free, and the
    parameters of the cameras in ``refine`` (the principal point only if
    ``principal_point``); two cameras fix the gauge; a Huber loss at ``options.ba_huber_px``.
    Returns (reconstruction, summary, mean reprojection error before, the adjuster)."""
    import pycolmap

    reconstruction = model_reconstruction(subset)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = ba.refine_extra_params = True
    ba.refine_principal_point = principal_point
    ba.refine_rig_from_world = ba.refine_points3D = True
    ba.print_summary = False
    ba.ceres.solver_options.max_num_iterations = 100
    ba.ceres.solver_options.function_tolerance = options.ba_function_tolerance
    ba.ceres.solver_options.num_threads = 1
    if options.ba_huber_px is not None:
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
        ba.ceres.loss_function_scale = options.ba_huber_px
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        if camera_id - offset not in refine:
            config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    error_before = reconstruction.compute_mean_reprojection_error()
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, config, reconstruction)
    summary = adjuster.solve()
    return reconstruction, summary, error_before, adjuster


def residual_sigma_px(reconstruction) -> float:
    """Per-coordinate sigma (px) of the reprojection residuals of ``reconstruction`` (a
    pycolmap Reconstruction) as it is now (:func:`reprojection_errors` of its scene): the
    median error norm / √(2 ln 2) (a Gaussian residual's norm is Rayleigh), so that the few
    points an adjustment sends far off do not count (castle-P19's OpenMVG matches: a mean of
    1e150 px after one adjustment), times √(n / (n − p)) for the p parameters the adjustment
    fitted to its n residual coordinates (3 per point, 6 per image). NaN without observations.
    The points' stored errors are not used: an adjustment does not update them (they were the
    errors before it)."""
    from rotonly_cli.io.colmap.model import scene_from_reconstruction

    errors = list(reprojection_errors(scene_from_reconstruction(reconstruction)).values())
    if not errors:
        return float("nan")
    errors = np.concatenate(errors)
    residuals = 2 * errors.size
    fitted = 3 * len(reconstruction.points3D) + 6 * len(reconstruction.reg_image_ids())
    dof = residuals / (residuals - fitted) if residuals > fitted else np.inf
    return float(np.nanmedian(errors) / np.sqrt(2.0 * np.log(2.0)) * np.sqrt(dof))


def _parameter_std(reconstruction, adjuster, camera_ids, offset: int,
                   options: IntrinsicsOptions) -> dict[int, np.ndarray]:
    """{camera (reconstruction id - ``offset``): standard deviation of each parameter} of the
    cameras ``camera_ids`` after the adjustment ``adjuster`` made: pycolmap's covariance of the
    problem ((JᵀJ)⁻¹ at unit noise) times the adjusted residuals' per-coordinate sigma
    (:func:`residual_sigma_px`). Cameras whose covariance is not available are left out, and
    all of them beyond ``options.covariance_max_images`` images (its cost grows as their cube)."""
    import pycolmap

    if len(reconstruction.reg_image_ids()) > options.covariance_max_images:
        return {}
    covariance = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), reconstruction, adjuster)
    if covariance is None:
        return {}
    sigma = residual_sigma_px(reconstruction)
    std = {}
    for camera_id in camera_ids:
        params = reconstruction.cameras[camera_id + offset].params
        block = covariance.get_other_params_cov(params)
        if block is not None and np.shape(block) == (len(params), len(params)):
            std[camera_id] = sigma * np.sqrt(np.maximum(np.diag(block), 0.0))
    return std


def _merged(subset: SfMScene, groups: list[list[int]]) -> SfMScene:
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


def _with_params(subset: SfMScene, params: dict[int, np.ndarray]) -> SfMScene:
    intrinsics = dict(subset.intrinsics)
    for camera_id, values in params.items():
        intrinsics[camera_id] = replace(intrinsics[camera_id], params=np.array(values, dtype=np.float64))
    return replace(subset, intrinsics=intrinsics)


def estimate_intrinsics(scene: SfMScene, refine: set[int], options: IntrinsicsOptions,
                        twins: list[list[int]] = ()) -> tuple[dict[int, Intrinsics], dict]:
    """Intrinsics of the cameras in ``refine`` (in :func:`io.cameras.refinement_model`
    terms) estimated by pycolmap's bundle adjuster on the posed ``scene``'s longest tracks,
    every pose, point and those cameras' parameters free (two cameras fix the gauge). The
    adjusted poses and points are discarded: only the intrinsics leave this function.

    The principal point is estimated per group of ``twins`` (cameras given identical
    intrinsics, :func:`twin_cameras`; a camera not named there is its own group), shared by
    the group's cameras, and only for a group seen in at least
    ``options.min_images_principal_point`` images; the other groups keep theirs. A shift of
    the principal point of one image is, to first order, a rotation of that camera
    (docs/algorithms.md §8), so only the images that share it pin it down. With a group of
    several cameras or a principal point kept, a first adjustment estimates the shared
    principal points (each group as one camera) and a second the focal lengths and
    distortion per camera, with the principal points held; a group whose focal the input
    marks known takes all of the first adjustment's camera instead."""
    start = time.perf_counter()
    models = {camera_id: cameras.refinement_model(intrinsic) for camera_id, intrinsic in scene.intrinsics.items()}
    unsupported = sorted(c for c in refine if models.get(c) is None)
    refine = {c for c in refine if models.get(c) is not None}
    subset = longest_tracks(scene, options.max_points, options.seed)
    subset = replace(subset, intrinsics={c: models[c] or cameras.to_colmap_intrinsics(k)
                                         for c, k in scene.intrinsics.items()})
    offset = id_offset(scene.intrinsics)
    grouped = {c for group in twins for c in group}
    groups = [[c for c in group if c in refine] for group in twins] + [[c] for c in sorted(refine - grouped)]
    groups = [group for group in groups if group]
    images = {c: 0 for c in refine}
    for view_id in subset.poses:
        camera_id = subset.views[view_id].intrinsics_id
        if camera_id in images:
            images[camera_id] += 1
    shared = [group for group in groups if sum(images[c] for c in group) >= options.min_images_principal_point]
    kept = [c for group in groups if group not in shared for c in group]
    merged = [group for group in shared if len(group) > 1]
    passes, whole = 1, set()
    std: dict[int, np.ndarray] = {}
    if not merged and not kept:
        reconstruction, summary, error_before, adjuster = _adjust(subset, refine, offset, options, True)
    elif not shared:
        reconstruction, summary, error_before, adjuster = _adjust(subset, refine, offset, options, False)
    else:
        passes = 2
        first, summary, error_before, adjuster = _adjust(_merged(subset, merged), refine, offset, options, True)
        params = {c: np.array(first.cameras[c + offset].params, dtype=np.float64) for c in refine
                  if c + offset in first.cameras}
        # a group whose focal the input does not call a guess (an EXIF focal: the same value,
        # the same zoom; OpenMVG's image listing without grouping) takes all of the group's
        # adjusted camera; a guessed one (COLMAP's one 1.2 x size guess can hide several
        # zooms) only its principal point, and each camera's own focal and distortion from the
        # second adjustment. One image's own focal is weakly fixed: castle-P19's database with
        # a camera per image, EXIF-like, moved view 16's by 1.9 %; its OpenMVG project with an
        # intrinsic per view moved view 3's by 3.9 % (0.170 deg; shared, 0.083 deg).
        whole = {c for group in merged if scene.intrinsics[group[0]].prior_focal is not False for c in group}
        # a group's cameras carry the uncertainty of the group's camera they take
        first_std = _parameter_std(first, adjuster, [group[0] for group in merged if group[0] in whole], offset,
                                   options)
        std = {c: first_std[group[0]] for group in merged if group[0] in first_std for c in group}
        for group in groups:
            pp = cameras.parameter_groups(subset.intrinsics[group[0]])["principal_point"]
            for camera_id in group:
                if camera_id in whole:
                    params[camera_id] = params[group[0]].copy()
                    continue
                # a merged group's other cameras start from the group's adjusted camera
                values = (params[camera_id] if camera_id in params else params[group[0]]).copy()
                # a group seen in too few images keeps its principal point; the others share
                # the one the group's images give
                values[pp] = (np.asarray(subset.intrinsics[camera_id].params)[pp] if group not in shared
                              else params[group[0]][pp])
                params[camera_id] = values
        if refine - whole:
            reconstruction, summary, _, adjuster = _adjust(_with_params(subset, params), refine - whole, offset,
                                                           options, False)
        else:
            passes, reconstruction, adjuster = 1, first, None
    if adjuster is not None:
        std.update(_parameter_std(reconstruction, adjuster, sorted(refine - whole), offset, options))
    reconstruction.update_point_3d_errors()
    error_after = reconstruction.compute_mean_reprojection_error()
    estimated, rejected = {}, []
    for camera_id in sorted(refine):
        values = params[camera_id] if camera_id in whole else reconstruction.cameras[camera_id + offset].params
        estimate = replace(models[camera_id], params=np.array(values, dtype=np.float64))
        if plausible(estimate):
            estimated[camera_id] = estimate
        else:
            rejected.append(camera_id)
    report = {"cameras": sorted(refine), "unsupported_models": unsupported, "implausible_estimates": rejected,
              "num_points": 0 if subset.structure is None else len(subset.structure.points),
              "num_images": len(reconstruction.reg_image_ids()),
              "principal_point_groups": shared, "principal_point_kept": sorted(kept),
              "adjustments": passes,
              "mean_reprojection_error_px": [float(error_before), float(error_after)],
              "termination": getattr(summary.termination_type, "name", str(summary.termination_type)),
              "estimate": {str(c): describe(k) for c, k in estimated.items()},
              "parameter_std": {str(c): std[c].tolist() for c in sorted(estimated) if c in std},
              "time_s": time.perf_counter() - start}
    return estimated, report


# ============================================================================ 4. significant changes

def _grid(intrinsic: Intrinsics, steps: int = 7) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, intrinsic.width, steps), np.linspace(0, intrinsic.height, steps))
    return np.column_stack([u.ravel(), v.ravel()])


def shift_px(reference: Intrinsics, other: Intrinsics) -> float:
    """How far ``other`` moves the image against ``reference``: the largest distance between a
    pixel of a grid over the image and where ``other`` puts that pixel's ray."""
    grid = _grid(reference)
    moved = cameras.project(other, cameras.normalize(reference, grid))
    distance = np.linalg.norm(moved - grid, axis=1)
    return float(np.nanmax(distance)) if np.isfinite(distance).any() else float("inf")


def shift_limit_px(intrinsics: Intrinsics, options: IntrinsicsOptions, noise_sigma_px: float | None = None) -> float:
    """The image shift (px) above which a change of ``intrinsics`` is significant:
    ``min_shift`` of its half diagonal, scaled up by the matches' noise beyond
    ``min_shift_noise_px`` (None: not measured, not scaled)."""
    scale = 1.0 if noise_sigma_px is None else max(1.0, noise_sigma_px / options.min_shift_noise_px)
    return options.min_shift * half_diagonal(intrinsics) * scale


def gate(reference: Intrinsics, estimate: Intrinsics, options: IntrinsicsOptions,
         always: frozenset[str] = frozenset(), noise_sigma_px: float | None = None,
         parameter_std: np.ndarray | None = None) -> tuple[Intrinsics, dict]:
    """``reference`` with the parameter groups (focal, principal point, distortion) of
    ``estimate`` whose change alone moves the image by more than :func:`shift_limit_px`
    (``min_shift`` of its half diagonal at low noise) and, given the estimate's
    ``parameter_std``, moves some parameter of the group by more than ``min_change_sigmas`` of
    them; and the groups in ``always`` whatever their change; all in refinement-model terms.
    Returns (camera, {group: shift in px})."""
    groups = cameras.parameter_groups(reference)
    limit = shift_limit_px(reference, options, noise_sigma_px)
    params = np.array(reference.params, dtype=np.float64)
    sigmas = change_sigmas(reference, estimate, parameter_std)
    shifts = {}
    for group in GROUPS:
        index = groups[group]
        if not index.size:
            continue
        candidate = np.array(reference.params, dtype=np.float64)
        candidate[index] = np.asarray(estimate.params)[index]
        shifts[group] = shift_px(reference, replace(reference, params=candidate))
        determined = sigmas is None or sigmas[group] > options.min_change_sigmas
        if (shifts[group] > limit and determined) or group in always:
            params[index] = np.asarray(estimate.params)[index]
    return replace(reference, params=params), shifts


def change_sigmas(reference: Intrinsics, estimate: Intrinsics, parameter_std: np.ndarray | None) -> dict | None:
    """{group: the largest change of a parameter of the group from ``reference`` to
    ``estimate`` in the estimate's standard deviations} (a held parameter, std 0, counts as
    determined: inf if it changed); None without ``parameter_std``."""
    if parameter_std is None:
        return None
    change = np.abs(np.asarray(estimate.params, dtype=np.float64) - np.asarray(reference.params, dtype=np.float64))
    std = np.asarray(parameter_std, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(std > 0, change / np.where(std > 0, std, 1.0), np.where(change > 0, np.inf, 0.0))
    return {group: float(z[index].max()) for group, index in cameras.parameter_groups(reference).items()
            if group in GROUPS and index.size}


def warnings_for(given: dict[int, Intrinsics], final: dict[int, Intrinsics], calibrated: set[int],
                 reprojection_px: float | None, options: IntrinsicsOptions) -> list[str]:
    """One line each: final mean reprojection error above ``warn_reprojection_px``; a camera
    not marked as a guess whose focal moved by more than ``warn_focal_change``."""
    warnings = []
    if reprojection_px is not None and reprojection_px > options.warn_reprojection_px:
        warnings.append(f"mean reprojection error {reprojection_px:.2f} px (> {options.warn_reprojection_px:g} px): "
                        f"the reconstruction does not fit the matches (intrinsics that --intrinsics {options.mode} "
                        f"did not put right, or poses bent by wrong matches)")
    for camera_id in sorted(final):
        if camera_id in calibrated and given[camera_id].prior_focal is False:
            continue  # a guess, expected to move
        change = final[camera_id].focal_px / given[camera_id].focal_px - 1.0
        if abs(change) > options.warn_focal_change:
            warnings.append(f"camera {camera_id}: focal moved {100 * change:+.1f} % from the given "
                            f"{given[camera_id].focal_px:.1f} px to {final[camera_id].focal_px:.1f} px")
    return warnings


# ============================================================================ the calibration of a run

def with_intrinsics(scene: SfMScene, changed: dict[int, Intrinsics]) -> SfMScene:
    """A copy of ``scene`` (sharing what does not change) with ``changed`` intrinsics and the
    keypoints of their views normalized again."""
    copy = replace(scene, intrinsics=dict(scene.intrinsics), normalized=dict(scene.normalized))
    cameras.renormalize(copy, changed)
    return copy


def with_focal(intrinsics: Intrinsics, focal_px: float, **changes) -> Intrinsics:
    """``intrinsics`` with its mean focal length (Intrinsics.focal_px) at ``focal_px``, the
    ratio of fx to fy kept, and ``changes`` (dataclass fields) applied."""
    params = np.array(intrinsics.params, dtype=np.float64)
    params[cameras.parameter_groups(intrinsics)["focal"]] *= focal_px / intrinsics.focal_px
    return replace(intrinsics, params=params, **changes)


def _same(a: Intrinsics, b: Intrinsics) -> bool:
    return a.model == b.model and np.array_equal(np.asarray(a.params), np.asarray(b.params))


@dataclass
class Calibration:
    """The intrinsics of one ``rotonly run``: as given, as they evolve, and the report.
    ``scene`` is the input scene with the current intrinsics (a new copy at every change, so
    runs made with earlier intrinsics keep theirs)."""

    options: IntrinsicsOptions
    given: dict[int, Intrinsics]
    scene: SfMScene
    #: cameras being calibrated, and why: "guess" (the input says so), "suspect" (its
    #: reprojection error), "refine" (--intrinsics refine)
    calibrate: dict[int, str] = field(default_factory=dict)
    #: per calibrated camera, what the estimates are compared with (refinement-model terms):
    #: the view-graph calibration's result for a guess, else the given intrinsics
    reference: dict[int, Intrinsics] = field(default_factory=dict)
    view_graph: list[dict] = field(default_factory=list)
    rounds: list[dict] = field(default_factory=list)
    first_reprojection_px: dict[int, float] = field(default_factory=dict)
    suspect_threshold_px: float | None = None
    noise_sigma_px: float | None = None  #: the matches' noise (F-based), when it was measured
    #: auto, when only suspects are calibrated: the run with the given intrinsics, the result
    #: if none of their changes is significant
    fallback: object | None = None
    settled: bool | None = None  #: whether the last round moved the intrinsics by little (None: no round)
    #: the report of :meth:`check_centred` (None: no camera was checked)
    centred_check: dict | None = None
    #: the report of the adjustment that confirms suspects (None: none to confirm)
    suspect_check: dict | None = None
    #: cameras one of those adjustments has looked at already
    adjusted_once: set = field(default_factory=set)
    result: dict = field(default_factory=dict)
    jobs: int = 1  #: processes for the fundamental-matrix fits
    #: wall time the calibration added to the run (view-graph focals, estimation passes and
    #: rounds; not the pass whose result is written)
    time_s: float = 0.0
    #: cameras this calibration added for images at another zoom (:meth:`_split`): {new
    #: camera: {"from": camera, "views": [...], "names": [...], "focal_px": its view-graph focal}}
    splits: dict[int, dict] = field(default_factory=dict)
    #: the report of :meth:`check_zoom` (None: not made)
    zoom_check: dict | None = None
    #: the report of :meth:`take_best_round` (None: the rounds settled)
    unsettled: dict | None = None
    #: per round (``rounds``), the scene with that round's estimate
    round_scenes: list = field(default_factory=list)

    def shift_limit_px(self, camera_id: int) -> float:
        """:func:`shift_limit_px` of a given camera at the matches' measured noise."""
        return shift_limit_px(self.given[camera_id], self.options, self.noise_sigma_px)

    def _calibrate_focals(self, cameras_: dict[int, str]) -> None:
        focals, report = view_graph_focals(self.scene, set(cameras_), self.options, self.jobs)
        self.view_graph.append(report)
        if set(cameras_) - set(focals):  # no fundamental matrix fixed them: a rotating camera?
            rotating, rotating_report = rotating_camera_focals(self.scene, set(cameras_) - set(focals), self.options)
            if rotating_report["cameras"]:
                self.view_graph.append(rotating_report)
            focals = {**focals, **rotating}
        self.scene = with_intrinsics(self.scene, focals)
        for camera_id, why in cameras_.items():
            self.calibrate[camera_id] = why
            # what an estimate must differ from to be kept: the view-graph calibration for a
            # focal the input calls a guess, else the intrinsics as given
            guess = self.given[camera_id].prior_focal is False
            self.reference[camera_id] = cameras.refinement_model(
                self.scene.intrinsics[camera_id] if guess else self.given[camera_id])
            if self.reference[camera_id] is None and not guess and camera_id in focals:
                # no refinement of this model: the view-graph focal is the only estimate, kept
                # if significant
                if shift_px(self.given[camera_id], focals[camera_id]) <= self.shift_limit_px(camera_id):
                    self.scene = with_intrinsics(self.scene, {camera_id: self.given[camera_id]})

    def check_zoom(self) -> bool:
        """Once, when the rounds have settled: do the images of each calibrated camera agree on
        its focal (:func:`per_image_focals`)? The check's cameras (:meth:`_check_camera`) take
        the rounds' distortion and focal, and the given principal point; images at another zoom
        get a camera of their own (:meth:`_split`). True if some did: the rounds go on.
        On the first view-graph calibration's cameras (no distortion yet), a simulated capture
        with k1 = -0.3 and the focal guessed 40 % long split its images at 2149 and 3112 px
        (true: 1380 for all); on the settled ones as they are, a zoom bends the principal
        point (Herz-Jesus-P8 with three images zoomed 5 %: 60 px), and the groups drown."""
        if not self.options.zoom_check or self.zoom_check is not None:
            return False
        start = time.perf_counter()
        # twins are one device, checked from one camera (the rounds gave a guess's twins a focal each)
        devices = twin_cameras(self.given, {c for c in self.calibrate if c not in self.splits})
        checked = {c: replace(self._check_camera(group), id=c) for group in devices for c in group}
        scene = with_intrinsics(self.scene, checked)
        fundamentals = refit_fundamentals(scene, self.options, self.jobs) if devices else {}
        self.zoom_check = per_image_focals(scene, devices, fundamentals, self.options) if fundamentals else {}
        split = [self._split(finding, checked) for finding in self.zoom_check.get("disagree", [])]
        self.zoom_check["time_s"] = time.perf_counter() - start
        self.time_s += self.zoom_check["time_s"]
        return any(split)

    def _check_camera(self, device: list[int]) -> Intrinsics:
        """The given camera of ``device`` (twins' camera ids) with the current distortion (its
        first camera's) and mean focal length (the given ratio of fx to fy kept): what the
        zoom check calibrates each image from."""
        given, current = self.given[device[0]], self.scene.intrinsics[device[0]]
        distortion = cameras.parameter_groups(given).get("distortion", [])
        params = np.array(given.params, dtype=np.float64)
        if current.model == given.model and len(distortion):
            params[distortion] = np.asarray(current.params, dtype=np.float64)[distortion]
        return with_focal(replace(given, params=params),
                          float(np.mean([self.scene.intrinsics[c].focal_px for c in device])))

    def _split(self, finding: dict, checked: dict[int, Intrinsics]) -> bool:
        """One camera's images at two focal lengths (a :func:`per_image_focals` finding on the
        ``checked`` cameras): the group whose focal lies farther from the camera's given one
        moves to a camera of its own, both restart from the checked camera with their group's
        focal, and the new one is calibrated as a guess from there (its ``given`` says so: the
        input's focal is wrong for those images). Only a camera of its own images; twins (a
        camera per image, the images of each group still tied by one focal) keep the warning."""
        camera_id = finding["camera"]
        if any(camera_id in group and len(group) > 1 for group in twin_cameras(self.given, self.given)):
            return False
        given_focal = self.given[camera_id].focal_px
        low, high = finding["groups"]
        move = max((low, high), key=lambda group: abs(np.log(group["focal_px"] / given_focal)))
        keep = high if move is low else low
        new_id = max(set(self.given) | set(self.scene.intrinsics)) + 1
        # Not a twin of the camera it came from: twins share the first adjustment's focal,
        # which bent a simulated capture's principal point by 18 px
        self.given[new_id] = with_focal(self.given[camera_id], move["focal_px"], id=new_id, prior_focal=False)
        views = {v: replace(view, intrinsics_id=new_id) if v in move["views"] else view
                 for v, view in self.scene.views.items()}
        self.scene = with_intrinsics(replace(self.scene, views=views), {
            new_id: with_focal(checked[camera_id], move["focal_px"], id=new_id),
            camera_id: with_focal(checked[camera_id], keep["focal_px"])})
        self.calibrate[new_id] = "zoom"
        self.reference[new_id] = cameras.refinement_model(self.scene.intrinsics[new_id])
        self.splits[new_id] = {"from": camera_id, "views": list(move["views"]), "names": list(move["names"]),
                               "focal_px": float(move["focal_px"])}
        logger.info("intrinsics: camera %d's images %s are at another zoom (%.0f px against %.0f px): camera %d, "
                    "calibrated on its own", camera_id, ", ".join(move["names"]), move["focal_px"], keep["focal_px"],
                    new_id)
        return True

    def add_suspects(self, sigma_by_camera: dict[str, float], scene: SfMScene,
                     posed: Callable[[], SfMScene] | None = None) -> bool:
        """auto: cameras not yet calibrated whose reprojection errors in the first
        reconstruction (``sigma_by_camera``: robust sigma in px of every observation's error
        before triangulation drops any, the triangulate stage's report) show them wrong join
        the calibration, starting with their focal from the view graph. True if any did.
        The matches' noise (``scene``'s) is measured only if some sigma is above the floor.
        ``posed``: makes that reconstruction, whose one adjustment (:meth:`_one_adjustment`) must
        confirm a suspect: the sigma alone cannot tell a camera 2 % off from a calibrated one
        (docs/tuning.md "Intrinsics"), and a suspect the adjustment leaves where it was would
        cost a round and a pass for the same result."""
        per_camera = {int(c): float(v) for c, v in sigma_by_camera.items()}
        self.first_reprojection_px = self.first_reprojection_px or per_camera  # a probe's came first
        noise = None
        if any(v > self.options.suspect_reprojection_px for v in per_camera.values()):
            noise = self.noise_sigma_px = projective_noise_sigma_px(scene, self.options)
        self.suspect_threshold_px = suspect_threshold_px(noise, self.options)
        suspects = suspect_cameras(per_camera, self.suspect_threshold_px)
        # twins are one device as the front end left it: what shows one of them wrong shows
        # the others (whose own errors may sit just below the threshold) and they are
        # calibrated together, sharing their principal point
        suspects = {c for group in twin_cameras(self.given, self.given) if suspects & set(group) for c in group
                    if c not in self.calibrate}
        if suspects:
            sigmas = ", ".join(f"{per_camera.get(c, float('nan')):.2f}" for c in sorted(suspects))
            if posed is not None:
                confirmed, self.suspect_check = self._one_adjustment(posed(), suspects)
                if not confirmed:
                    logger.info("intrinsics: camera(s) %s reproject with sigma %s px (> %.2f px), but one adjustment "
                                "moves them by less than %.1f px or within %g standard deviations of its estimate: "
                                "kept as given", sorted(suspects), sigmas, self.suspect_threshold_px,
                                min(self.shift_limit_px(c) for c in suspects), self.options.min_change_sigmas)
                    return False
            logger.info("intrinsics: camera(s) %s reproject with sigma %s px (> %.2f px): calibrating them",
                        sorted(suspects), sigmas, self.suspect_threshold_px)
            self._calibrate_focals(dict.fromkeys(sorted(suspects), "suspect"))
        return bool(suspects)

    def _gated_estimates(self, posed: SfMScene, camera_ids: set[int], reference: dict[int, Intrinsics],
                         guesses: frozenset[int] = frozenset()) -> tuple[dict[int, Intrinsics], dict]:
        """One :func:`estimate_intrinsics` of ``camera_ids`` on the reconstruction ``posed``
        (twins sharing), each camera's estimate gated against its ``reference`` (:func:`gate`;
        the focal of a camera in ``guesses`` always taken): {camera: intrinsics as the input's
        model}, and the report with the shifts."""
        estimated, report = estimate_intrinsics(posed, camera_ids, self.options, twin_cameras(self.given, camera_ids))
        gated, shifts, sigmas = {}, {}, {}
        for camera_id, estimate in estimated.items():
            # a focal the input marks as a guess has no value to protect: the view-graph focal
            # is a start, and the estimate is better on average (algorithms.md §8 "Significant
            # changes only"); the other groups change when significant
            always = frozenset({"focal"}) if camera_id in guesses else frozenset()
            std = report["parameter_std"].get(str(camera_id))
            std = None if std is None else np.array(std)
            camera, shifts[camera_id] = gate(reference[camera_id], estimate, self.options, always,
                                             self.noise_sigma_px, std)
            gated[camera_id] = cameras.from_refinement_model(self.given[camera_id], camera)
            sigmas[camera_id] = change_sigmas(reference[camera_id], estimate, std)
        report["shifts_px"] = {str(c): v for c, v in shifts.items()}
        report["change_sigmas"] = {str(c): v for c, v in sigmas.items() if v is not None}
        return gated, report

    def _changes(self, before: dict[int, Intrinsics], after: dict[int, Intrinsics]) -> tuple[dict, float]:
        """The cameras of ``after`` that differ from ``before``, and the largest image shift
        that makes, as a fraction of the half diagonal."""
        changed = {c: k for c, k in after.items() if not _same(k, before[c])}
        moved = max((shift_px(before[c], k) / half_diagonal(before[c]) for c, k in changed.items()), default=0.0)
        return changed, moved

    def _one_adjustment(self, posed: SfMScene, checked: set[int]) -> tuple[dict[int, Intrinsics], dict]:
        """The cameras of ``checked`` whose estimate from the reconstruction ``posed`` (one
        :func:`estimate_intrinsics`, twins sharing) differs significantly from the given
        intrinsics (:func:`gate`): {camera: gated intrinsics}, and the report."""
        gated, report = self._gated_estimates(posed, checked, {c: cameras.refinement_model(self.given[c])
                                                               for c in checked})
        changed, moved = self._changes(self.given, gated)
        report.update(calibrated=sorted(changed), moved=moved)
        self.time_s += report["time_s"]
        self.adjusted_once |= set(checked)
        return changed, report

    def check_centred(self, posed: Callable[[], SfMScene]) -> bool:
        """auto: cameras marked known (not yet calibrated) whose principal point sits at the
        image centre (:func:`centred_principal_point`) are checked by one estimate from the
        first reconstruction (``posed`` makes it); those it moves significantly (:func:`gate` against
        the given intrinsics) join the calibration, starting from the gated estimate. True if
        any did. The reprojection errors cannot show such a camera: an 11 px principal point
        error leaves them at calibrated cameras' level (docs/tuning.md "Intrinsics")."""
        tolerance = self.options.centred_principal_point_px
        if tolerance is None:
            return False
        checked = {c for c, k in self.given.items() if c not in self.calibrate and c not in self.adjusted_once
                   and k.prior_focal is not False
                   and cameras.refinement_model(k) is not None and centred_principal_point(k, tolerance)}
        if not checked:
            return False
        changed, report = self._one_adjustment(posed(), checked)
        for camera_id in changed:
            self.calibrate[camera_id] = "centred principal point"
            self.reference[camera_id] = cameras.refinement_model(self.given[camera_id])
        self.centred_check = report
        shifts, sigmas = report["shifts_px"], report["change_sigmas"]
        logger.info("intrinsics: camera(s) %s have their principal point at the image centre (a default); "
                    "one adjustment moves them by %s px (limit %s), %s standard deviations of its estimate "
                    "(limit %g): %s", sorted(checked),
                    ", ".join(f"{max(shifts.get(str(c), {}).values(), default=0.0):.1f}" for c in sorted(checked)),
                    ", ".join(f"{self.shift_limit_px(c):.1f}" for c in sorted(checked)),
                    ", ".join(f"{max(sigmas[str(c)].values(), default=0.0):.1f}" if str(c) in sigmas else "?"
                              for c in sorted(checked)),
                    self.options.min_change_sigmas, f"calibrating {sorted(changed)}" if changed else "kept as given")
        if changed:
            self.scene = with_intrinsics(self.scene, changed)
        return bool(changed)

    def estimate(self, posed: SfMScene) -> bool:
        """One round: the intrinsics estimated from the reconstruction ``posed``, each change
        kept when significant (:func:`gate`); ``scene`` takes the new intrinsics. True when
        they moved the image by no more than ``converged_shift`` and the focal lengths by no
        more than ``converged_focal_change`` (settled)."""
        gated, report = self._gated_estimates(posed, set(self.calibrate), self.reference,
                                              frozenset(c for c, why in self.calibrate.items() if why == "guess"))
        changed, moved = self._changes(self.scene.intrinsics, gated)
        focal_change = max((abs(k.focal_px / self.scene.intrinsics[c].focal_px - 1.0) for c, k in changed.items()),
                           default=0.0)
        self.scene = with_intrinsics(self.scene, changed) if changed else self.scene
        report.update(moved=moved, focal_change=focal_change,
                      result={str(c): describe(self.scene.intrinsics[c]) for c in sorted(self.calibrate)})
        self.rounds.append(report)
        self.round_scenes.append(self.scene)
        logger.info("intrinsics: round %d (%.2f s): %s", len(self.rounds), report["time_s"], self._calibrated_text())
        self.settled = moved <= self.options.converged_shift and focal_change <= self.options.converged_focal_change
        return self.settled

    def take_best_round(self) -> None:
        """Rounds that did not settle: the calibrated cameras take the estimate of the round
        whose adjustment converged on the most points (the least bent reconstruction keeps the
        most tracks), else of the round with the most points; the report's ``unsettled`` names
        it."""
        def rank(report: dict) -> tuple[bool, int]:
            return report.get("termination") == "CONVERGENCE", int(report.get("num_points") or 0)

        best = max(range(len(self.rounds)), key=lambda k: rank(self.rounds[k]))
        chosen = self.round_scenes[best]
        changed = {c: chosen.intrinsics[c] for c in self.calibrate
                   if c in chosen.intrinsics and not _same(chosen.intrinsics[c], self.scene.intrinsics[c])}
        if changed:
            self.scene = with_intrinsics(self.scene, changed)
        self.unsettled = {"taken_round": best + 1,
                          "rounds": [{"num_points": report.get("num_points"), "termination": report.get("termination")}
                                     for report in self.rounds],
                          "result": {str(c): describe(self.scene.intrinsics[c]) for c in sorted(self.calibrate)}}
        converged, points = rank(self.rounds[best])
        logger.info("intrinsics: the rounds did not settle; round %d's estimate, its adjustment %s on %d points, is "
                    "taken: %s", best + 1, "converged" if converged else "not converged", points,
                    self._calibrated_text())

    def _calibrated_text(self) -> str:
        """The calibrated cameras' current parameters, for the log."""
        return "; ".join(f"camera {c} {np.round(self.scene.intrinsics[c].params, 4).tolist()}"
                         for c in sorted(self.calibrate))

    def moved_from(self, scene: SfMScene) -> bool:
        """True if the current intrinsics moved the image of some camera by more than
        ``converged_shift`` from ``scene``'s (whose load stage then no longer fits)."""
        return any(c not in scene.intrinsics or shift_px(scene.intrinsics[c], self.scene.intrinsics[c])
                   / half_diagonal(scene.intrinsics[c]) > self.options.converged_shift for c in self.calibrate)

    def back_to_given(self) -> bool:
        """True when there is a fallback run and every camera is back to its given intrinsics
        (never after a split: the fallback gave the split images the other focal)."""
        return self.fallback is not None and not self.splits and all(_same(self.scene.intrinsics[c], k)
                                                                     for c, k in self.given.items())

    def finish(self, posed: SfMScene) -> dict:
        """The report (reports/intrinsics.json) of the run's final reconstruction ``posed``."""
        per_camera, overall = mean_reprojection_errors(posed)
        final = {c: posed.intrinsics[c] for c in self.given}
        warnings = warnings_for(self.given, final, set(self.calibrate), overall, self.options)
        split_to = {split["from"]: new_id for new_id, split in self.splits.items()}
        twins = {c for group in twin_cameras(self.given, self.given) if len(group) > 1 for c in group}
        warnings += [zoom_warning(finding, split_to.get(finding["camera"]), finding["camera"] in twins)
                     for finding in (self.zoom_check or {}).get("disagree", [])]
        for camera_id, intrinsic in self.given.items():
            if intrinsic.prior_focal is False and camera_id not in self.calibrate:
                warnings.append(f"camera {camera_id}: its focal length is marked as a guess (prior_focal_length = 0) "
                                f"and is used as given (--intrinsics {self.options.mode})")
        self.result = {
            "mode": str(self.options.mode),
            "cameras": {str(c): {"start": describe(self.given[c]), "end": describe(final[c]),
                                 "calibrated": self.calibrate.get(c), "prior_focal": self.given[c].prior_focal,
                                 "focal_change": final[c].focal_px / self.given[c].focal_px - 1.0,
                                 "reprojection_error_px": per_camera.get(c),
                                 "first_reprojection_sigma_px": self.first_reprojection_px.get(c)}
                        for c in sorted(self.given)},
            "reprojection_error_px": overall, "view_graph_calibration": self.view_graph, "rounds": self.rounds,
            "settled": self.settled, "suspect_threshold_px": self.suspect_threshold_px,
            "centred_principal_point_check": self.centred_check, "suspect_check": self.suspect_check,
            "noise_sigma_px": self.noise_sigma_px,
            "zoom_check": self.zoom_check, "unsettled": self.unsettled,
            "split_cameras": {str(c): split for c, split in self.splits.items()},
            "kept_given_intrinsics": all(_same(final[c], k) for c, k in self.given.items()),
            "warnings": warnings, "time_s": self.time_s}
        return self.result

    def changed(self) -> dict:
        """For the workspace state: the mode and the cameras whose intrinsics differ from the
        input's ({id: {"model", "params"}}), so that the stage commands use the same."""
        cameras_ = {str(c): {"model": k.model, "params": [float(v) for v in np.asarray(k.params).ravel()]}
                    for c, k in self.scene.intrinsics.items() if c in self.given and not _same(k, self.given[c])}
        splits = {str(c): {"from": split["from"], "views": split["views"], "focal_px": split["focal_px"]}
                  for c, split in self.splits.items()}
        return {"mode": str(self.options.mode), "cameras": cameras_, **({"splits": splits} if splits else {})} \
            if cameras_ or splits else {}

    def restore(self, saved: dict) -> None:
        """The intrinsics of :meth:`changed` (saved by an earlier command) in place of the input's."""
        restored = {}
        for key, split in (saved or {}).get("splits", {}).items():  # the cameras a zoom check added
            camera_id, source = int(key), int(split["from"])
            if source not in self.given or camera_id in self.given or not set(split["views"]) <= set(self.scene.views):
                raise InputError("the workspace's split camera does not fit the input",
                                 field=f"state.npz options.intrinsics.splits[{key}]")
            self.given[camera_id] = with_focal(self.given[source], float(split["focal_px"]), id=camera_id,
                                               prior_focal=False)
            views = {v: replace(view, intrinsics_id=camera_id) if v in split["views"] else view
                     for v, view in self.scene.views.items()}
            self.scene = with_intrinsics(replace(self.scene, views=views), {camera_id: self.given[camera_id]})
            self.splits[camera_id] = {"from": source, "views": list(split["views"]),
                                      "focal_px": float(split["focal_px"])}
        for key, camera in (saved or {}).get("cameras", {}).items():
            camera_id = int(key)
            if camera_id not in self.given:
                raise InputError("the workspace's intrinsics name a camera the input does not have",
                                 field=f"state.npz options.intrinsics.cameras[{key}]")
            restored[camera_id] = replace(self.given[camera_id], model=camera["model"],
                                          params=np.asarray(camera["params"], dtype=np.float64))
            self.calibrate[camera_id] = "restored"
        if restored:
            self.scene = with_intrinsics(self.scene, restored)

    def summary(self) -> dict:
        """The run summary's part: intrinsics at start and end per camera, the final mean
        reprojection error, the warnings."""
        return {"intrinsics": {c: {"start": v["start"]["params"], "end": v["end"]["params"],
                                   "model": [v["start"]["model"], v["end"]["model"]]}
                               for c, v in self.result["cameras"].items()},
                "reprojection_error_px": self.result["reprojection_error_px"], "warnings": self.result["warnings"]}


def start_calibration(scene: SfMScene, options: IntrinsicsOptions, calibrate_now: bool = True,
                      jobs: int = 1) -> Calibration:
    """The calibration of a run on ``scene`` as read: the cameras to calibrate from the start
    get their focal length from the view graph (before the load stage) if ``calibrate_now``."""
    options.validate()
    calibration = Calibration(options, dict(scene.intrinsics), scene, jobs=jobs)
    calibrate = cameras_to_calibrate(scene, options.mode) if calibrate_now else set()
    if calibrate:
        why = "refine" if options.mode == Mode.REFINE else "guess"
        calibration._calibrate_focals(dict.fromkeys(sorted(calibrate), why))
    return calibration
