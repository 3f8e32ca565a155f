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

from rotonly_cli.calibration.guesses import guess_missing_cameras
from rotonly_cli.calibration.rounds import Calibration, start_calibration

__all__ = ["Calibration", "guess_missing_cameras", "start_calibration"]
