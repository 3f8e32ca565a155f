"""io/cameras.py: one interface over COLMAP and OpenMVG camera models, and the COLMAP model
pycolmap refines in place of each; COLMAP's prior_focal_length through the database."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.io import cameras, colmap
from rotonly_cli.scene.types import Intrinsics, SfMScene, View


def _grid(width=1536, height=1024):
    u, v = np.meshgrid(np.linspace(1, width - 1, 9), np.linspace(1, height - 1, 7))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("intrinsics", [
    Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0, 770.0, 510.0, -0.2])),
    Intrinsics(1, "PINHOLE", 1536, 1024, np.array([1380.0, 1385.0, 770.0, 510.0])),
    Intrinsics(0, "pinhole", 1536, 1024, np.array([1380.0, 770.0, 510.0])),
    Intrinsics(0, "pinhole_radial_k1", 1536, 1024, np.array([1380.0, 770.0, 510.0, 0.25])),
    Intrinsics(0, "pinhole_radial_k3", 1536, 1024, np.array([1380.0, 770.0, 510.0, -0.1, 0.02, 0.0])),
])
def test_normalize_and_project_are_inverse(intrinsics):
    pixels = _grid()
    np.testing.assert_allclose(cameras.project(intrinsics, cameras.normalize(intrinsics, pixels)), pixels, atol=1e-6)


def test_refinement_model_adds_a_radial_term_and_maps_back():
    pinhole = Intrinsics(0, "pinhole", 1536, 1024, np.array([1380.0, 770.0, 510.0]))
    model = cameras.refinement_model(pinhole)
    assert model.model == "SIMPLE_RADIAL" and model.params.tolist() == [1380.0, 770.0, 510.0, 0.0]
    same = cameras.from_refinement_model(pinhole, model)
    assert same.model == "pinhole" and same.params.tolist() == [1380.0, 770.0, 510.0]
    refined = cameras.from_refinement_model(pinhole, Intrinsics(0, "SIMPLE_RADIAL", 1536, 1024,
                                                                np.array([1300.0, 760.0, 500.0, 0.1])))
    assert refined.model == "pinhole_radial_k1" and refined.params.tolist() == [1300.0, 760.0, 500.0, 0.1]

    simple = Intrinsics(1, "SIMPLE_PINHOLE", 1536, 1024, np.array([1380.0, 770.0, 510.0]))
    assert cameras.from_refinement_model(simple, Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024,
                                                            np.array([1.0, 2.0, 3.0, 0.2]))).model == "SIMPLE_RADIAL"
    k3 = Intrinsics(0, "pinhole_radial_k3", 1536, 1024, np.array([1380.0, 770.0, 510.0, -0.1, 0.02, 0.0]))
    assert cameras.refinement_model(k3).model == "RADIAL"
    back = cameras.from_refinement_model(k3, Intrinsics(0, "RADIAL", 1536, 1024, np.array([1.0, 2.0, 3.0, 0.1, 0.2])))
    assert back.model == "pinhole_radial_k3" and back.params.tolist() == [1.0, 2.0, 3.0, 0.1, 0.2, 0.0]
    opencv = Intrinsics(1, "OPENCV", 1536, 1024, np.array([1380.0, 1382.0, 770.0, 510.0, 0.1, 0.0, 0.0, 0.0]))
    assert cameras.refinement_model(opencv).model == "OPENCV"
    # OpenMVG models whose COLMAP counterpart has terms OpenMVG cannot hold: not refined
    brown = Intrinsics(0, "pinhole_brown_t2", 1536, 1024, np.array([1380.0, 770.0, 510.0, 0.1, 0, 0, 0, 0]))
    assert cameras.refinement_model(brown) is None


def test_parameter_groups():
    assert {k: v.tolist() for k, v in cameras.parameter_groups(
        Intrinsics(1, "PINHOLE", 10, 10, np.array([5.0, 5.0, 5.0, 5.0]))).items()} == {
        "focal": [0, 1], "principal_point": [2, 3], "distortion": []}
    assert {k: v.tolist() for k, v in cameras.parameter_groups(
        Intrinsics(0, "pinhole_radial_k3", 10, 10, np.array([5.0, 5.0, 5.0, 0, 0, 0]))).items()} == {
        "focal": [0], "principal_point": [1, 2], "distortion": [3, 4, 5]}


def test_renormalize_changes_only_the_views_of_the_camera():
    scene = SfMScene()
    first = Intrinsics(1, "SIMPLE_PINHOLE", 100, 100, np.array([100.0, 50.0, 50.0]))
    second = Intrinsics(2, "SIMPLE_PINHOLE", 100, 100, np.array([200.0, 50.0, 50.0]))
    scene.intrinsics = {1: first, 2: second}
    for view_id, camera_id in ((1, 1), (2, 2)):
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", camera_id)
        scene.keypoints[view_id] = np.array([[60.0, 70.0]])
        scene.normalized[view_id] = cameras.normalize(scene.intrinsics[camera_id], scene.keypoints[view_id])
    untouched = scene.normalized[2]
    cameras.renormalize(scene, {1: Intrinsics(1, "SIMPLE_PINHOLE", 100, 100, np.array([50.0, 50.0, 50.0]))})
    np.testing.assert_allclose(scene.normalized[1], [[0.2, 0.4]])
    assert scene.normalized[2] is untouched


def test_prior_focal_length_round_trips_through_a_database(tmp_path):
    scene = SfMScene()
    scene.intrinsics = {1: Intrinsics(1, "SIMPLE_RADIAL", 100, 80, np.array([120.0, 50.0, 40.0, 0.0]),
                                      prior_focal=False),
                        2: Intrinsics(2, "SIMPLE_RADIAL", 100, 80, np.array([90.0, 50.0, 40.0, 0.0]))}
    for view_id in (1, 2):
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", view_id)
        scene.keypoints[view_id] = np.zeros((0, 2))
    colmap.write_database(tmp_path / "database.db", scene)
    read = colmap.read_database(tmp_path / "database.db")
    assert read.intrinsics[1].prior_focal is False
    assert read.intrinsics[2].prior_focal is True  # not marked a guess: written as known
