"""Cameras as users have them (guessed focal lengths, unknown distortion): the calibration of
``--intrinsics auto|refine`` (docs/algorithms.md §8), by concern:

1. guesses: which cameras are calibrated (marked guesses, suspects, centred principal points,
   twins); noise: the matches' noise that makes a camera a suspect;
2. focals: focal lengths from the view graph, before any rotation is estimated;
3. adjustment: intrinsics from a reconstruction, and which of their changes are significant;
4. rounds: the Calibration of a run, whose rounds chain/calibrate.py drives.

rotonly's rotation stages work on normalized coordinates, so they are only as good as the
intrinsics that make them; the poses rotonly writes are always the product of its
rotation-only stages.
"""

from rotonly_cli.calibration.adjustment import (
    change_sigmas,
    estimate_intrinsics,
    gate,
    half_diagonal,
    residual_sigma_px,
    shift_limit_px,
    shift_px,
)
from rotonly_cli.calibration.focals import (
    focal_groups,
    per_image_focals,
    refit_fundamentals,
    view_graph_focals,
    zoom_warning,
)
from rotonly_cli.calibration.guesses import (
    cameras_to_calibrate,
    centred_principal_point,
    guess_missing_cameras,
    suspect_cameras,
    suspect_threshold_px,
    twin_cameras,
)
from rotonly_cli.calibration.noise import homography_noise_sigma_px, projective_noise_sigma_px
from rotonly_cli.calibration.rounds import Calibration, start_calibration, warnings_for, with_focal, with_intrinsics

__all__ = ["Calibration", "cameras_to_calibrate", "centred_principal_point", "change_sigmas", "estimate_intrinsics",
           "focal_groups", "gate", "guess_missing_cameras", "half_diagonal", "homography_noise_sigma_px",
           "per_image_focals", "projective_noise_sigma_px", "refit_fundamentals", "residual_sigma_px",
           "shift_limit_px", "shift_px", "start_calibration", "suspect_cameras", "suspect_threshold_px",
           "twin_cameras", "view_graph_focals", "warnings_for", "with_focal", "with_intrinsics", "zoom_warning"]
