"""Point colours: mean RGB over the observations' pixels, images decoded on threads."""

from __future__ import annotations

import cv2
import numpy as np

from rotonly_cli.scene.types import SfMScene, View
from rotonly_cli.stages.triangulate import GREY, keypoint_colors, point_colors

from helpers import dies_in_a_child


def test_point_colors_are_mean_rgb_of_observed_pixels(tmp_path):
    rng = np.random.default_rng(4)
    scene = SfMScene()
    view_ids = [3, 5, 8, 9]
    images = {}
    for view_id in view_ids:
        scene.views[view_id] = View(view_id, f"sub/img{view_id}.png", 1)
        scene.keypoints[view_id] = rng.uniform(0, 40, (30, 2))
        scene.keypoints[view_id][0] = [40.0, 30.0]  # the far edge: clipped to the last pixel
        if view_id != 8:  # view 8: missing image -> its observations give no colour
            images[view_id] = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)  # BGR
            (tmp_path / "sub").mkdir(exist_ok=True)
            assert cv2.imwrite(str(tmp_path / "sub" / f"img{view_id}.png"), images[view_id])
    num_points = 50
    obs_point = rng.integers(0, num_points - 1, 120)  # point 49 is never observed
    obs_view_row = rng.integers(0, 4, 120)
    obs_feature = rng.integers(0, 30, 120)
    colors, report = point_colors(scene, tmp_path, view_ids, obs_point, obs_view_row, obs_feature, num_points)

    sums, hits = np.zeros((num_points, 3)), np.zeros(num_points)
    for point, row, feature in zip(obs_point, obs_view_row, obs_feature):
        view_id = view_ids[row]
        if view_id not in images:
            continue
        u, v = np.minimum(np.floor(scene.keypoints[view_id][feature]).astype(int), [39, 29])
        sums[point] += images[view_id][v, u, ::-1]
        hits[point] += 1
    expected = np.full((num_points, 3), GREY, dtype=np.uint8)
    expected[hits > 0] = np.round(sums[hits > 0] / hits[hits > 0, None]).astype(np.uint8)
    np.testing.assert_array_equal(colors, expected)
    assert report["images_missing"] == ["sub/img8.png"]
    assert report["points_coloured"] == int((hits > 0).sum()) and 30 < report["points_coloured"] < 49
    assert tuple(colors[49]) == (GREY, GREY, GREY)

    grey, report = point_colors(scene, None, view_ids, obs_point, obs_view_row, obs_feature, num_points)
    assert np.all(grey == GREY) and report["points_coloured"] == 0

    # precomputed keypoint colours (as triangulate_graph prefetches them on a thread)
    sequential = keypoint_colors(scene, tmp_path, view_ids, threads=1)
    threaded = keypoint_colors(scene, tmp_path, view_ids, threads=2)
    assert sequential[8] is None and threaded[8] is None
    for view_id in (3, 5, 9):
        np.testing.assert_array_equal(sequential[view_id], threaded[view_id])
        assert sequential[view_id].shape == (30, 3) and sequential[view_id].dtype == np.uint8
    np.testing.assert_array_equal(sequential[3][0], images[3][29, 39, ::-1])
    again, _ = point_colors(scene, tmp_path, view_ids, obs_point, obs_view_row, obs_feature, num_points, sequential)
    np.testing.assert_array_equal(again, expected)
    partial = {3: sequential[3]}  # views missing from the prefetch are read again
    again, report = point_colors(scene, tmp_path, view_ids, obs_point, obs_view_row, obs_feature, num_points, partial)
    np.testing.assert_array_equal(again, expected)
    assert report["images_missing"] == ["sub/img8.png"]


def _scene_with_images(tmp_path):
    rng = np.random.default_rng(6)
    scene = SfMScene()
    for view_id in (1, 2, 3):
        scene.views[view_id] = View(view_id, f"v{view_id}.png", 1)
        scene.keypoints[view_id] = rng.uniform(0, 20, (15 + view_id, 2))
        if view_id != 2:  # view 2: no image file
            assert cv2.imwrite(str(tmp_path / f"v{view_id}.png"), rng.integers(0, 256, (20, 20, 3), dtype=np.uint8))
    return scene


def test_forked_keypoint_colors_equal_decoding_here(tmp_path):
    import os

    from rotonly_cli.stages.triangulate import ForkedKeypointColors

    scene = _scene_with_images(tmp_path)
    forked = ForkedKeypointColors(scene, tmp_path, [1, 2, 3])
    assert forked._call._process.pid != os.getpid()
    colors = forked.result(timeout=30)
    direct = keypoint_colors(scene, tmp_path, [1, 2, 3], threads=1)
    assert colors[2] is None and direct[2] is None
    for view_id in (1, 3):
        np.testing.assert_array_equal(colors[view_id], direct[view_id])
        assert colors[view_id].shape == (15 + view_id, 3)


def test_a_failed_decoding_process_falls_back_to_decoding_here(tmp_path, monkeypatch, caplog):

    from rotonly_cli.stages.triangulate import ForkedKeypointColors

    # the child dies, this process decodes
    monkeypatch.setattr(ForkedKeypointColors, "_decode", dies_in_a_child(ForkedKeypointColors._decode, 3))
    scene = _scene_with_images(tmp_path)
    colors = ForkedKeypointColors(scene, tmp_path, [1, 2, 3]).result(timeout=30)
    assert "exit code 3" in caplog.text
    direct = keypoint_colors(scene, tmp_path, [1, 2, 3], threads=1)
    for view_id in (1, 3):
        np.testing.assert_array_equal(colors[view_id], direct[view_id])
