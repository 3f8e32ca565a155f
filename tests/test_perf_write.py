"""Speed paths of `rotonly run` after GRRM give the same results as the plain paths:
flat observation arrays carried beside ``Structure.observations``, keypoint colours
decoded on a thread started early."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import openmvg
from rotonly_cli.io.colmap import colmap_to_openmvg
from rotonly_cli.scene.ids import observation_lists, renumber_views_by_name
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View
from rotonly_cli.stages.triangulate import keypoint_colors, start_keypoint_colors


def _posed_scene(rng: np.random.Generator, with_arrays: bool) -> SfMScene:
    """Views 1..5 named in reverse id order, random tracks of length 2-4 over them."""
    scene = SfMScene(source="colmap-db")
    scene.intrinsics[1] = Intrinsics(1, "SIMPLE_PINHOLE", 640, 480, np.array([500.0, 320.0, 240.0]))
    for view_id in range(1, 6):
        scene.views[view_id] = View(view_id, f"img{9 - view_id}.jpg", 1)
        scene.keypoints[view_id] = rng.uniform(0, 400, (40, 2))
        scene.poses[view_id] = Pose(np.eye(3), np.array([0.1 * view_id, 0.0, -5.0]))
    lengths = rng.integers(2, 5, 30)
    view_feature = np.concatenate([np.stack([np.sort(rng.choice(np.arange(1, 6), n, replace=False)),
                                             rng.integers(0, 40, n)], axis=1) for n in lengths])
    observations = observation_lists(lengths, view_feature)
    scene.structure = Structure(np.arange(1, 31, dtype=np.int64), rng.normal(size=(30, 3)),
                                rng.integers(0, 256, (30, 3), dtype=np.uint8), observations,
                                observation_arrays=(lengths, view_feature) if with_arrays else None)
    return scene


def test_observation_lists_and_flat_arrays_agree():
    lengths = np.array([2, 0, 3])
    view_feature = np.array([[4, 10], [7, 2], [1, 0], [4, 5], [9, 9]])
    lists = observation_lists(lengths, view_feature)
    assert lists == [[(4, 10), (7, 2)], [], [(1, 0), (4, 5), (9, 9)]]
    plain = Structure(np.arange(3), np.zeros((3, 3)), observations=lists)
    flat_lengths, flat = plain.flat_observations()
    np.testing.assert_array_equal(flat_lengths, lengths)
    np.testing.assert_array_equal(flat, view_feature)
    stale = replace(plain, observations=lists[:2], observation_arrays=(lengths, view_feature))
    with pytest.raises(InputError):
        stale.flat_observations()


def test_convert_remaps_arrays_and_lists_alike():
    """colmap_to_openmvg + renumber_views_by_name (what run's writer does) on a structure
    with and without ``observation_arrays``: same observations, the arrays follow the lists."""
    with_arrays = renumber_views_by_name(colmap_to_openmvg(_posed_scene(np.random.default_rng(3), True)))
    plain = renumber_views_by_name(colmap_to_openmvg(_posed_scene(np.random.default_rng(3), False)))
    assert with_arrays.structure.observations == plain.structure.observations
    lengths, view_feature = with_arrays.structure.observation_arrays
    assert observation_lists(lengths, view_feature) == plain.structure.observations
    # view 5 (name img4.jpg) is the first by name -> id 0; view 1 (img8.jpg) the last -> 4
    first = plain.structure.observations[0]
    original = _posed_scene(np.random.default_rng(3), False).structure.observations[0]
    assert [v for v, _ in first] == [5 - v for v, _ in original]
    assert openmvg.sfm_data_bytes(with_arrays) == openmvg.sfm_data_bytes(plain)


def test_early_keypoint_colors_equal_decoding_in_triangulate(tmp_path):
    rng = np.random.default_rng(5)
    scene = SfMScene()
    for view_id in (2, 4, 6):
        scene.views[view_id] = View(view_id, f"v{view_id}.png", 1)
        scene.keypoints[view_id] = rng.uniform(0, 30, (25, 2))
        if view_id != 4:  # view 4: no image file
            assert cv2.imwrite(str(tmp_path / f"v{view_id}.png"),
                               rng.integers(0, 256, (30, 30, 3), dtype=np.uint8))
    future = start_keypoint_colors(scene, tmp_path)
    early = future.result(timeout=30)
    direct = keypoint_colors(scene, tmp_path, [2, 4, 6], threads=1)
    assert early[4] is None and direct[4] is None
    for view_id in (2, 6):
        np.testing.assert_array_equal(early[view_id], direct[view_id])
        assert early[view_id].shape == (25, 3)
    assert start_keypoint_colors(scene, None) is None


def test_collector_paused_restores_the_collector_state():
    import gc

    from rotonly_cli.runtime.startup import collector_paused

    assert gc.isenabled()
    with pytest.raises(RuntimeError):
        with collector_paused():
            assert not gc.isenabled()
            raise RuntimeError("a failing stage")
    assert gc.isenabled()  # back on after an error
    gc.disable()
    try:
        with collector_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()  # a caller's choice (off) is kept
    finally:
        gc.enable()
