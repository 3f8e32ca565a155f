"""Vectorised writers: the OpenMVG ``structure`` text and the float/int formatting give the
same bytes as plain json.dumps over a per-landmark Python reference."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import openmvg
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View


def _awkward_floats(rng: np.random.Generator) -> np.ndarray:
    """Values around the repr notation switches (1e-4, 1e16), signed zeros, subnormals,
    extremes, float32-derived pixels and random bit patterns."""
    edges = np.array([1e-4, 1e16, 1e-5, 1e15, 1e22, 5e-324, 2.2250738585072014e-308,
                      1e308, 0.1, 0.5, 1.0, 100.0, 123456.789])
    around = np.concatenate([edges, np.nextafter(edges, 0), np.nextafter(edges, np.inf),
                             [1.7976931348623157e308]])
    bits = rng.integers(0, 2 ** 63, size=20000, dtype=np.int64).view(np.float64)
    bits = bits[np.isfinite(bits)]
    pixels = rng.uniform(0, 3000, 20000).astype(np.float32).astype(np.float64) - 0.5
    return np.concatenate([around, -around, [0.0, -0.0], bits, -bits[:100],
                           10.0 ** rng.uniform(-6, 18, 20000), pixels])


def test_float_and_integer_texts_equal_python_repr():
    values = _awkward_floats(np.random.default_rng(3))
    assert openmvg.sfm_data_writer._float_reprs(values) == [repr(v) for v in values.tolist()]
    assert openmvg.sfm_data_writer._float_reprs(values.reshape(-1, 1)[:6]) == [repr(v) for v in values[:6].tolist()]
    integers = np.array([0, 1, 9, 10, 4294967295, 123456789012, -3], dtype=np.int64)
    assert openmvg.sfm_data_writer._integer_texts(integers) == ["0", "1", "9", "10", "4294967295", "123456789012", "-3"]
    assert openmvg.sfm_data_writer._float_reprs(np.zeros(0)) == []
    assert openmvg.sfm_data_writer._integer_texts(np.zeros(0)) == []


def _reference_structure(scene: SfMScene) -> list:
    """The structure document written the slow, obvious way (one landmark at a time)."""
    structure = scene.structure
    rows = []
    for point_index in np.argsort(structure.point_ids, kind="stable"):
        track = structure.observations[point_index]
        by_view = sorted(range(len(track)), key=lambda row: track[row][0])
        observations = []
        for row in by_view:
            view_id, feature = track[row]
            if structure.observation_pixels is not None:
                pixel = structure.observation_pixels[point_index][row]
            elif view_id in scene.keypoints and feature < len(scene.keypoints[view_id]):
                pixel = scene.keypoints[view_id][feature]
            else:  # projection through the pinhole camera
                pose = scene.poses[view_id]
                x_cam = pose.R_cam_from_world @ (structure.points[point_index] - pose.center)
                f, cx, cy = scene.intrinsics[scene.views[view_id].intrinsics_id].params
                pixel = np.array([x_cam[0] / x_cam[2] * f + cx, x_cam[1] / x_cam[2] * f + cy])
            observations.append({"key": int(view_id), "value": {
                "id_feat": int(feature), "x": [float(pixel[0]) - 0.5, float(pixel[1]) - 0.5]}})
        rows.append({"key": int(structure.point_ids[point_index]), "value": {
            "X": [float(v) for v in structure.points[point_index]], "observations": observations}})
    return rows


def _scene(rng: np.random.Generator, num_points: int, stored_pixels: bool) -> SfMScene:
    scene = SfMScene(root_path="/img")
    scene.intrinsics[0] = Intrinsics(0, "pinhole", 640, 480, np.array([500.0, 320.25, 240.5]))
    for view_id in range(6):
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", 0)
        angle = 0.1 * view_id
        R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        scene.poses[view_id] = Pose(R, np.array([0.3 * view_id, 0.0, -5.0]))
        if view_id != 5:  # view 5: no keypoints -> projection
            scene.keypoints[view_id] = rng.uniform(0, 640, (50, 2)).astype(np.float32).astype(np.float64)
    observations, pixels = [], []
    for _ in range(num_points):
        views = rng.permutation(6)[:rng.integers(0, 5)]  # unsorted views, some empty tracks
        features = rng.integers(0, 60, len(views))  # some beyond the keypoints -> projection
        observations.append([(int(v), int(k)) for v, k in zip(views, features)])
        pixels.append(rng.uniform(-1, 700, (len(views), 2)))
    point_ids = rng.permutation(10 * num_points)[:num_points]
    points = rng.normal(size=(num_points, 3)) * np.array([1, 1, 0.2])
    points[0] = [1e-5, -0.0, 3e20]
    scene.structure = Structure(point_ids, points, None, observations, pixels if stored_pixels else None)
    return scene


# the landmarks in one piece / a few observations (a landmark or two, with empty ones) at a time
@pytest.mark.parametrize("observations_per_piece", [1 << 16, 1, 5])
@pytest.mark.parametrize("stored_pixels", [True, False])
def test_structure_text_equals_json_dumps_of_reference(monkeypatch, stored_pixels, observations_per_piece):
    monkeypatch.setattr(openmvg.sfm_data_writer, "OBSERVATIONS_PER_PIECE", observations_per_piece)
    scene = _scene(np.random.default_rng(11), 400, stored_pixels)
    expected = json.dumps(_reference_structure(scene), indent=4)
    # the structure array sits at indent level 1 inside the document
    expected = expected.replace("\n", "\n    ")
    assert openmvg.sfm_data_writer._structure_text(scene) == expected
    document = json.loads(openmvg.sfm_data_bytes(scene))
    assert document["structure"] == json.loads(expected)
    assert sum(len(row["value"]["observations"]) == 0 for row in document["structure"]) > 10


def test_structure_text_single_landmarks():
    scene = _scene(np.random.default_rng(2), 1, True)
    scene.structure.observations[0] = []
    scene.structure.observation_pixels[0] = np.zeros((0, 2))
    assert openmvg.sfm_data_writer._structure_text(scene) == json.dumps(_reference_structure(scene), indent=4).replace(
        "\n", "\n    ")
    scene.structure.observations[0] = [(4, 1), (2, 3)]
    scene.structure.observation_pixels[0] = np.array([[1.5, 2.5], [3.5, 4.5]])
    text = openmvg.sfm_data_writer._structure_text(scene)
    assert json.loads(text)[0]["value"]["observations"] == [
        {"key": 2, "value": {"id_feat": 3, "x": [3.0, 4.0]}},
        {"key": 4, "value": {"id_feat": 1, "x": [1.0, 2.0]}}]
    scene.structure = Structure(np.zeros(0, np.int64), np.zeros((0, 3)), None, [], None)
    assert openmvg.sfm_data_writer._structure_text(scene) == "[]"


def test_structure_writer_rejects_bad_landmarks():
    scene = _scene(np.random.default_rng(5), 20, True)
    scene.structure.observations[3] = [(1, 2), (1, 5)]
    scene.structure.observation_pixels[3] = np.zeros((2, 2))
    with pytest.raises(InputError, match="two observations in one view") as error:
        openmvg.sfm_data_bytes(scene)
    assert error.value.field == f"structure[{int(scene.structure.point_ids[3])}]"
    scene = _scene(np.random.default_rng(5), 20, True)
    scene.structure.observation_pixels[4] = np.zeros((7, 2))
    with pytest.raises(InputError, match="observation_pixels"):
        openmvg.sfm_data_bytes(scene)
    scene = _scene(np.random.default_rng(5), 20, True)
    scene.structure.points[2, 1] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        openmvg.sfm_data_bytes(scene)
    scene = _scene(np.random.default_rng(5), 20, False)
    del scene.poses[5]
    scene.structure.observations[0] = [(5, 3)]
    with pytest.raises(InputError, match=r"no pixel position for observation \(view 5, feature 3\)"):
        openmvg.sfm_data_bytes(scene)
