"""calibration/loose.py: guessed focal lengths the matches cannot determine (issue 51 item 3)."""

from __future__ import annotations

import numpy as np

from rotonly_cli.calibration.loose import loose_focals, loose_warning
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import Intrinsics, SfMScene, View

GUESS = Intrinsics(1, "PINHOLE", 1280, 960, np.array([1000.0, 1000.0, 640.0, 480.0]), prior_focal=False)


def _scene(cameras: dict[int, Intrinsics], camera_of_view: dict[int, int]) -> SfMScene:
    return SfMScene(intrinsics=cameras, views={v: View(v, f"{v}.jpg", c) for v, c in camera_of_view.items()})


def test_twins_without_fundamental_matrices_share_and_a_lone_image_keeps_its_guess():
    """Cameras 1-3: one guess given to three images (a camera per image), 0 / 2 / 5
    fundamental matrices; camera 4: its own guess on one image, none; camera 5: its own
    guess on two images, none (a camera over a plane: the rounds fix one shared focal);
    camera 6: a known focal, none."""
    other = GUESS.params * np.array([1.1, 1.1, 1, 1])
    cameras = {1: GUESS, 2: GUESS, 3: GUESS, 4: Intrinsics(4, "PINHOLE", 1280, 960, other, prior_focal=False),
               5: Intrinsics(5, "PINHOLE", 1280, 960, other * np.array([1.1, 1.1, 1, 1]), prior_focal=False),
               6: Intrinsics(6, "PINHOLE", 1280, 960, GUESS.params, prior_focal=True)}
    scene = _scene(cameras, {1: 1, 2: 2, 3: 3, 4: 4, 5: 5, 6: 5, 7: 6})
    pairs = {"1": 0, "2": 2, "3": 5, "4": 0, "5": 0, "6": 0}
    shared, held = loose_focals(cameras, scene, pairs, IntrinsicsOptions())
    assert shared == {1, 2} and held == {4}
    # one fundamental matrix is a little epipolar geometry: that lone image is calibrated
    assert loose_focals(cameras, scene, {**pairs, "4": 1}, IntrinsicsOptions())[1] == set()
    [line] = loose_warning(cameras, cameras, shared, held, IntrinsicsOptions())
    assert "camera(s) 1, 2 share one focal length" in line and "(1000 px)" in line
    assert "camera(s) 4 keep the given focal length (1100 px)" in line
    assert loose_warning(cameras, cameras, set(), set(), IntrinsicsOptions()) == []
