"""Which tracks the intrinsics' bundle adjustment sees (calibration/adjustment.longest_tracks):
the longest, at most ``max_points`` of them and at most the ones holding ``max_observations``
observations (on long tracks its memory grows with the observations, not the points)."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.calibration.adjustment import longest_tracks
from rotonly_cli.errors import InputError
from rotonly_cli.options import IntrinsicsOptions
from rotonly_cli.scene.types import SfMScene, Structure


def _scene(lengths: list[int]) -> SfMScene:
    observations = [[(view, point) for view in range(n)] for point, n in enumerate(lengths)]
    points = np.arange(3 * len(lengths), dtype=float).reshape(-1, 3)
    return SfMScene(structure=Structure(np.arange(len(lengths), dtype=np.int64) + 100, points,
                                        observations=observations))


def test_the_longest_tracks_up_to_the_points_and_the_observations():
    scene = _scene([3, 9, 2, 7, 5, 8, 4])
    by_points = longest_tracks(scene, max_points=3).structure
    assert by_points.point_ids.tolist() == [101, 103, 105]  # lengths 9, 7, 8, in the scene's order
    # 9 + 8 + 7 = 24 <= 25 < 24 + 5: three of the five longest
    by_observations = longest_tracks(scene, max_points=5, max_observations=25).structure
    assert by_observations.point_ids.tolist() == [101, 103, 105]
    assert [len(o) for o in by_observations.observations] == [9, 7, 8]
    np.testing.assert_array_equal(by_observations.points, scene.structure.points[[1, 3, 5]])
    assert longest_tracks(scene, max_points=5, max_observations=3).structure.point_ids.tolist() == [101]  # one at least


def test_a_scene_within_both_limits_is_returned_as_it_is():
    scene = _scene([3, 9, 2])
    assert longest_tracks(scene, max_points=3, max_observations=14) is scene
    assert longest_tracks(scene, max_points=3, max_observations=13) is not scene


def test_max_observations_below_a_thousand_is_refused():
    with pytest.raises(InputError):
        IntrinsicsOptions(max_observations=999).validate()
    assert IntrinsicsOptions(max_observations=1000).validate().max_observations == 1000
