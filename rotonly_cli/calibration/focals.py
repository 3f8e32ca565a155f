"""Focal lengths from the view graph (calibration/, step 2), before any rotation is estimated:
F re-fitted on every verified pair's matches, then ``pycolmap.calibrate_view_graph`` —
COLMAP's port of GLOMAP's ViewGraphCalibrator (Fetzer et al., WACV 2020), not a copy of it —
on a private database in a temporary folder; the focal of a rotating camera where no pair
holds an F; and the zoom check (do the images of one camera agree on its focal?). The load
stage then re-estimates every relative pose with a calibrated E."""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rotonly_cli.calibration.guesses import (
    merged_twins,
    twin_cameras,
)
from rotonly_cli.calibration.noise import NO_FUNDAMENTAL
from rotonly_cli.io import cameras
from rotonly_cli.io.colmap.database import read_camera_params, write_fundamental_database
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.runtime.parallel import edge_parts, fork_map
from rotonly_cli.scene.types import Intrinsics, SfMScene

logger = logging.getLogger(__name__)

#: the F re-fit forks a process per this many matches at most (a fork costs ~30 ms)
MIN_MATCHES_PER_PROCESS = 20_000


def refit_fundamentals(scene: SfMScene, options: IntrinsicsOptions, jobs: int = 1) -> dict[tuple[int, int], np.ndarray]:
    """F of every verified pair that can hold one, from pycolmap's LO-RANSAC with Sampson
    refinement on the pair's matches, in pixels without the cameras' known distortion (the
    keypoints themselves when there is none). COLMAP 3.8 stores F without that refinement,
    which costs the view-graph focal percents (docs/tuning.md). ``jobs``: processes (forked)."""
    import pycolmap

    ransac = pycolmap.RANSACOptions(max_error=options.fundamental_max_error_px, random_seed=options.seed,
                                    min_num_trials=options.fundamental_min_trials)
    pixels = {view_id: cameras.undistorted_pixels(scene.intrinsics[view.intrinsics_id], scene.normalized[view_id])
              for view_id, view in scene.views.items() if view_id in scene.normalized}
    keys = [key for key, pair in sorted(scene.pairs.items()) if pair.verified and pair.config not in NO_FUNDAMENTAL
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


def fundamental_pairs_by_camera(scene: SfMScene, fundamentals: dict[tuple[int, int], np.ndarray],
                                camera_ids) -> dict[str, int]:
    """{camera of ``camera_ids``: how many of ``fundamentals``' pairs have a view of it}: the
    pairs whose epipolar geometry says something of its focal length (a plane or a pure
    rotation holds no fundamental matrix: NO_FUNDAMENTAL)."""
    counts = dict.fromkeys(sorted(camera_ids), 0)
    for i, j in fundamentals:
        for camera_id in {scene.views[i].intrinsics_id, scene.views[j].intrinsics_id}:
            if camera_id in counts:
                counts[camera_id] += 1
    return {str(c): n for c, n in counts.items()}


def view_graph_focals(scene: SfMScene, calibrate: set[int], options: IntrinsicsOptions,
                      jobs: int = 1) -> tuple[dict[int, Intrinsics], dict]:
    """New intrinsics (only the focal length changed) of the cameras in ``calibrate``, by
    ``pycolmap.calibrate_view_graph`` over the re-fitted fundamental matrices; the other
    cameras are held constant. Cameras given identical intrinsics (:func:`twin_cameras`:
    COLMAP's camera per image) are calibrated as one, as in the first adjustment of a round:
    a camera per image has fewer fundamental matrices than cameras, and a focal each went far
    off. Twins whose focal the input gives (an EXIF camera per image, calibrated as suspects)
    share it too (docs/tuning.md "Measurements behind the code")."""
    start = time.perf_counter()
    fundamentals = refit_fundamentals(scene, options, jobs)
    report = {"cameras": sorted(calibrate), "num_pairs": len(fundamentals),
              "fundamental_pairs_by_camera": fundamental_pairs_by_camera(scene, fundamentals, calibrate),
              "refit_time_s": time.perf_counter() - start}
    if len(fundamentals) < options.min_fundamental_pairs:
        report.update(success=False, time_s=time.perf_counter() - start)
        if fundamentals:
            logger.info("intrinsics: view-graph calibration skipped: %d pair(s) with a fundamental matrix (< %d)",
                        len(fundamentals), options.min_fundamental_pairs)
        return {}, report
    groups = [group for group in twin_cameras(scene.intrinsics, calibrate) if len(group) > 1]
    owner = {camera_id: group[0] for group in groups for camera_id in group}
    merged = merged_twins(scene, groups) if groups else scene
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
    taken at two, and no shared calibration fits both (docs/tuning.md "Intrinsics")."""
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
    scatter by half a per cent and, where few pairs hold a fundamental matrix, by tens of per
    cent with no gap between groups (docs/tuning.md "Measurements behind the code")."""
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
#: (a panorama) has H = K R K⁻¹, which fixes the focal length where no F can (NO_FUNDAMENTAL)
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


