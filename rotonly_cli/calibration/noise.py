"""The matches' noise sigma whatever the focal lengths (calibration/, step 1): the threshold
above which a camera's reprojection errors make it a suspect. Fundamental matrices on the
largest verified pairs, homographies where too few pairs hold one."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rotonly_cli.io import cameras
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import SfMScene

#: two-view configurations whose matches do not constrain a fundamental matrix (a plane or a
#: pure rotation: the homography's F family is degenerate), left out of the calibration
NO_FUNDAMENTAL = ("PLANAR", "PLANAR_OR_PANORAMIC", "PANORAMIC", "H", "DEGENERATE", "UNDEFINED", "WATERMARK")

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
    for pair in _noise_sample(scene, lambda config: config not in NO_FUNDAMENTAL, options):
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


