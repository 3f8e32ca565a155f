"""Intrinsics from a reconstruction (calibration/, step 3) and which of their changes count
(step 4).

Once rotonly has rotations, centres and points, pycolmap's bundle adjuster estimates focal,
principal point and radial terms on the longest tracks (:func:`estimate_intrinsics`; one
principal point per set of twin cameras seen in at least two images). It moves poses and
points too (with them held, K barely moves: docs/tuning.md "Intrinsics"), but it serves only
as an intrinsics estimator: its poses and points are discarded. A change of the focal, the
principal point or the distortion is kept (:func:`gate`) when it moves some pixel of the
image by more than ``min_shift`` of its half diagonal and by more than ``min_change_sigmas``
of the estimate's standard deviations: refining parameters that were right costs accuracy."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from rotonly_cli.calibration.guesses import (
    merged_twins,
    reprojection_errors,
)
from rotonly_cli.io import cameras
from rotonly_cli.io.colmap import id_offset
from rotonly_cli.io.colmap.model import model_reconstruction
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import Intrinsics, SfMScene

GROUPS = ("focal", "principal_point", "distortion")
#: pycolmap chooses its iterative Schur solver above this many images (1000 by default); the
#: adjustment's tracks are bounded by IntrinsicsOptions.max_observations, so the direct one stays small
DIRECT_SPARSE_MAX_IMAGES = 1_000_000


def half_diagonal(intrinsics: Intrinsics) -> float:
    return 0.5 * float(np.hypot(intrinsics.width, intrinsics.height))


def describe(intrinsics: Intrinsics) -> dict:
    """JSON form of a camera for the reports."""
    return {"model": intrinsics.model, "width": int(intrinsics.width), "height": int(intrinsics.height),
            "params": [float(v) for v in np.asarray(intrinsics.params, dtype=float).ravel()],
            "focal_px": intrinsics.focal_px}



def plausible(intrinsics: Intrinsics) -> bool:
    """Finite parameters, positive focal lengths, the principal point inside the image."""
    params = np.asarray(intrinsics.params, dtype=np.float64)
    groups = cameras.parameter_groups(intrinsics)
    cx, cy = params[groups["principal_point"]]
    return bool(np.all(np.isfinite(params)) and np.all(params[groups["focal"]] > 0)
                and 0 <= cx <= intrinsics.width and 0 <= cy <= intrinsics.height)


def longest_tracks(scene: SfMScene, max_points: int, seed: int = 0, max_observations: int | None = None) -> SfMScene:
    """``scene`` with only its ``max_points`` longest tracks (ties broken at random, seeded),
    and of those no more than hold ``max_observations`` observations: the adjustment's memory
    and time (and its covariance's) grow with the observations: on the 200-view circle of
    docs/results.md "Scale" they took the run to its peak, 543 MB above their start on the 5000
    longest tracks, 259 MB on the 1576 that hold 100 000 (docs/tuning.md)."""
    structure = scene.structure
    if structure is None:
        return scene
    lengths, _ = structure.flat_observations()
    if len(lengths) <= max_points and (max_observations is None or int(np.sum(lengths)) <= max_observations):
        return scene
    order = np.lexsort((np.random.default_rng(seed).random(len(lengths)), -lengths))[:max_points]
    if max_observations is not None:
        within = np.cumsum(lengths[order]) <= max_observations
        order = order[:max(int(within.sum()), 1)]
    keep = np.sort(order)
    subset = replace(structure, point_ids=np.asarray(structure.point_ids)[keep],
                     points=np.asarray(structure.points)[keep],
                     colors=None if structure.colors is None else np.asarray(structure.colors)[keep],
                     observations=[structure.observations[k] for k in keep.tolist()],
                     observation_pixels=None, observation_arrays=None)
    return replace(scene, structure=subset)



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
    # the direct sparse Schur solver at every size: pycolmap's iterative one above 1000 images
    # took 110 s on the 10 000-view strip's 1984 longest tracks (docs/tuning.md "Intrinsics")
    ba.ceres.max_num_images_direct_sparse_cpu_solver = DIRECT_SPARSE_MAX_IMAGES
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
    points an adjustment sends far off do not count (their mean can be astronomical), times
    √(n / (n − p)) for the p parameters the adjustment fitted to its n residual coordinates (3
    per point, 6 per image). NaN without observations. The points' stored errors are not used:
    an adjustment does not update them (they were the errors before it)."""
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


def _with_params(subset: SfMScene, params: dict[int, np.ndarray]) -> SfMScene:
    intrinsics = dict(subset.intrinsics)
    for camera_id, values in params.items():
        intrinsics[camera_id] = replace(intrinsics[camera_id], params=np.array(values, dtype=np.float64))
    return replace(subset, intrinsics=intrinsics)


def estimate_intrinsics(scene: SfMScene, refine: set[int], options: IntrinsicsOptions,
                        twins: list[list[int]] = (), shared_focal: frozenset[int] = frozenset(),
                        ) -> tuple[dict[int, Intrinsics], dict]:
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
    subset = longest_tracks(scene, options.max_points, options.seed, options.max_observations)
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
        first, summary, error_before, adjuster = _adjust(merged_twins(subset, merged), refine, offset, options, True)
        params = {c: np.array(first.cameras[c + offset].params, dtype=np.float64) for c in refine
                  if c + offset in first.cameras}
        # a group whose focal the input does not call a guess (an EXIF focal: the same value,
        # the same zoom; OpenMVG's image listing without grouping) takes all of the group's
        # adjusted camera; a guessed one (COLMAP's one 1.2 x size guess can hide several
        # zooms) only its principal point, and each camera's own focal and distortion from the
        # second adjustment. One image's own focal is weakly fixed (it moved by percents).
        # Twins in ``shared_focal`` (guesses whose images hold too few fundamental matrices to
        # tell their focal lengths apart: a plane) take it too.
        whole = {c for group in merged for c in group
                 if scene.intrinsics[group[0]].prior_focal is not False or c in shared_focal}
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


