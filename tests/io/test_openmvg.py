"""rotonly_cli.io.openmvg: OpenMVG sfm_data.json, camera models, .feat, matches, projects."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import openmvg
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, Structure, View

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES / "openmvg_real"
CUT_PROJECT = FIXTURES / "cut_project"

# One intrinsic of every supported type: [focal, ppx, ppy (COLMAP convention), k...].
MODELS = {
    "pinhole": [1380.91, 760.595, 503.655],
    "pinhole_radial_k1": [1200.0, 640.5, 360.5, -0.12],
    "pinhole_radial_k3": [1100.0, 700.25, 480.75, -0.21, 0.09, -0.02],
    "pinhole_brown_t2": [1000.0, 650.0, 500.0, -0.15, 0.05, -0.01, 0.001, -0.0015],
    "fisheye": [700.0, 640.0, 480.0, 0.03, -0.01, 0.004, -0.001],
}


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _synthetic_scene(rng: np.random.Generator) -> SfMScene:
    """Five views over all five intrinsic types (two views share one), a rig pose shared by
    two views, a view in a sub-folder, a view without intrinsic/pose, and structure."""
    scene = SfMScene(root_path="/data/images", source="simulation")
    for intrinsic_id, (model, params) in enumerate(MODELS.items()):
        scene.intrinsics[intrinsic_id] = Intrinsics(intrinsic_id, model, 1280, 960,
                                                    np.array(params))
    layout = [  # view id, name, intrinsic, pose id
        (0, "a/img0.jpg", 0, 0), (1, "img1.jpg", 1, 1), (2, "img2.png", 2, 2),
        (3, "img3.jpg", 3, 3), (4, "img4.jpg", 4, 3), (5, "img5.jpg", 0, 5),
        (6, "unknown.jpg", openmvg.UNDEFINED_INDEX, openmvg.UNDEFINED_INDEX),
    ]
    for view_id, name, intrinsic_id, pose_id in layout:
        scene.views[view_id] = View(view_id, name, intrinsic_id, pose_id,
                                    width=1280 if view_id < 6 else 4000,
                                    height=960 if view_id < 6 else 3000)
    for view_id in (0, 1, 2, 3, 5):
        scene.poses[view_id] = Pose(_rotation(rng), rng.normal(size=3))
    scene.poses[4] = Pose(scene.poses[3].R_cam_from_world.copy(), scene.poses[3].center.copy())
    # 511.7 / 1023.9 / 0.3 cross binade boundaries when 0.5 is added: the writer must still be
    # byte-stable.
    pixels = [np.array([[511.7, 0.3], [1023.9, 1.2]]), np.array([[10.25, 20.5], [30.0, 40.0]]),
              np.array([[5.0, 6.0], [7.0, 8.0], [9.0, 10.0]])]
    scene.structure = Structure(
        point_ids=np.array([7, 3, 11]), points=rng.normal(size=(3, 3)), colors=None,
        observations=[[(0, 4), (1, 9)], [(2, 0), (3, 1)], [(5, 2), (1, 3), (0, 8)]],
        observation_pixels=pixels)
    return scene


# =============================================================================== real files

def test_real_sfm_data_reads_views_and_intrinsics():
    scene = openmvg.read_sfm_data(FIXTURES / "sfm_data.json")
    assert scene.source == "openmvg" and scene.root_path == "../images"
    assert sorted(scene.views) == list(range(8))
    assert [scene.views[i].name for i in range(8)] == [f"{i:04d}.jpg" for i in range(8)]
    assert all(v.intrinsics_id == 0 and v.pose_id == v.id for v in scene.views.values())
    assert (scene.views[5].width, scene.views[5].height) == (1536, 1024)
    intrinsic = scene.intrinsics[0]
    assert intrinsic.model == "pinhole" and (intrinsic.width, intrinsic.height) == (1536, 1024)
    # File: focal 1380.91, principal point (760.095, 503.155) in OpenMVG's convention.
    np.testing.assert_allclose(intrinsic.params, [1380.91, 760.595, 503.655], rtol=0, atol=1e-12)
    assert scene.poses == {} and scene.structure is None


def test_real_global_sfm_data_reads_poses():
    scene = openmvg.read_sfm_data(FIXTURES / "global_sfm_data.json")
    raw = json.loads((FIXTURES / "global_sfm_data.json").read_text())
    assert sorted(scene.poses) == list(range(8))
    raw_poses = {item["key"]: item["value"] for item in raw["extrinsics"]}
    for view_id, pose in scene.poses.items():
        np.testing.assert_array_equal(pose.R_cam_from_world, raw_poses[view_id]["rotation"])
        np.testing.assert_array_equal(pose.center, raw_poses[view_id]["center"])
        np.testing.assert_allclose(pose.R_cam_from_world @ pose.R_cam_from_world.T, np.eye(3),
                                   atol=1e-9)
    # A value read off the file by eye: the first row of pose 7's rotation.
    np.testing.assert_allclose(scene.poses[7].R_cam_from_world[0],
                               [0.7432336923245179, 0.09410801246662995, 0.6623800726042749])


def _canonical(document: dict) -> dict:
    """sfm_data JSON with map entries sorted by key and pointer ids dropped (OpenMVG's own
    order is unordered_map order)."""
    out = {"version": document["sfm_data_version"], "root": document["root_path"]}
    for key in ("views", "intrinsics", "extrinsics", "structure", "control_points"):
        items = sorted(document[key], key=lambda item: item["key"])
        for item in items:
            item["value"].get("ptr_wrapper", {}).pop("id", None)
        out[key] = items
    return out


def test_rewriting_real_global_file_keeps_every_value():
    scene = openmvg.read_sfm_data(FIXTURES / "global_sfm_data.json")
    ours = json.loads(openmvg.sfm_data_bytes(scene))
    theirs = json.loads((FIXTURES / "global_sfm_data.json").read_text())
    assert _canonical(ours) == _canonical(theirs)


def test_real_matches_bin_counts_and_bytes():
    path = FIXTURES / "matches.e.bin"
    matches = openmvg.read_matches(path)
    assert len(matches) == 22
    assert sum(len(m) for m in matches.values()) == 22687
    assert len(matches[(0, 1)]) == 1595 and len(matches[(5, 6)]) == 2555
    assert all(i < j for i, j in matches)
    # cereal layout: 9 header bytes + 16 per pair + 8 per match.
    assert path.stat().st_size == 9 + 16 * 22 + 8 * 22687
    # Re-writing reproduces OpenMVG's file byte for byte.
    assert openmvg.matches_bytes(matches, binary=True) == path.read_bytes()


def test_read_project_on_cut_real_project():
    scene = openmvg.read_project(CUT_PROJECT / "sfm_data.json")
    for view_id in range(8):
        feat = CUT_PROJECT / f"{view_id:04d}.feat"
        lines = feat.read_text().splitlines()
        assert len(scene.keypoints[view_id]) == len(lines)
        first = [float(v) for v in lines[0].split()[:2]]
        np.testing.assert_allclose(scene.keypoints[view_id][0], np.add(first, 0.5), atol=1e-12)
        # pinhole: normalized = (pixel - principal point) / focal
        expected = (scene.keypoints[view_id] - [760.595, 503.655]) / 1380.91
        np.testing.assert_allclose(scene.normalized[view_id], expected, atol=1e-15)
    assert len(scene.pairs) == 22
    assert sum(len(p.matches) for p in scene.pairs.values()) == 332
    pair = scene.pairs[(2, 3)]
    assert pair.config == "E" and pair.verified and (pair.i, pair.j) == (2, 3)
    assert pair.matches.dtype == np.int64
    for (i, j), pair in scene.pairs.items():
        assert pair.matches[:, 0].max() < len(scene.keypoints[i])
        assert pair.matches[:, 1].max() < len(scene.keypoints[j])


def test_read_project_putative_file_is_unverified(tmp_path):
    scene = openmvg.read_project(CUT_PROJECT / "sfm_data.json",
                                 matches_file=CUT_PROJECT / "matches.putative.txt")
    assert sum(len(p.matches) for p in scene.pairs.values()) == 334
    assert all(not p.verified and p.config is None for p in scene.pairs.values())
    # Default preference: without matches.e.* the putative file is taken.
    for path in CUT_PROJECT.iterdir():
        if path.name != "matches.e.bin":
            shutil.copy(path, tmp_path / path.name)
    scene = openmvg.read_project(tmp_path / "sfm_data.json")
    assert len(scene.pairs) == 22 and not scene.pairs[(0, 1)].verified


# =============================================================================== writer rules

def test_write_read_write_is_byte_identical(tmp_path):
    scene = _synthetic_scene(np.random.default_rng(1))
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    openmvg.write_sfm_data(first, scene)
    openmvg.write_sfm_data(second, openmvg.read_sfm_data(first))
    assert first.read_bytes() == second.read_bytes()
    real = openmvg.read_sfm_data(FIXTURES / "global_sfm_data.json")
    openmvg.write_sfm_data(first, real)
    openmvg.write_sfm_data(second, openmvg.read_sfm_data(first))
    assert first.read_bytes() == second.read_bytes()


def test_written_sfm_data_follows_every_writer_rule(tmp_path):
    scene = _synthetic_scene(np.random.default_rng(2))
    path = tmp_path / "sfm_data.json"
    openmvg.write_sfm_data(path, scene)
    text = path.read_text()
    document = json.loads(text)
    assert "\n    \"views\": [\n        {" in text  # rapidjson-style 4-space pretty print
    # All 7 top-level keys, in Save_Cereal's order, version 0.3 (§1.1).
    assert list(document) == ["sfm_data_version", "root_path", "views", "intrinsics",
                              "extrinsics", "structure", "control_points"]
    assert document["sfm_data_version"] == "0.3" and document["control_points"] == []
    assert document["root_path"] == "/data/images"

    # One ptr_wrapper counter over views then intrinsics, from 2147483649 (§1.2).
    views, intrinsics = document["views"], document["intrinsics"]
    ptr_ids = [item["value"]["ptr_wrapper"]["id"] for item in views + intrinsics]
    assert ptr_ids == list(range(2147483649, 2147483649 + len(views) + len(intrinsics)))
    assert all(item["value"]["polymorphic_id"] == 1073741824 for item in views)
    assert all("polymorphic_name" not in item["value"] for item in views)
    # Each new type name: 0x80000000 | k with its name; 5 distinct types here.
    assert [(item["value"]["polymorphic_id"], item["value"].get("polymorphic_name"))
            for item in intrinsics] == [(2147483649, "pinhole"), (2147483650, "pinhole_radial_k1"),
                                        (2147483651, "pinhole_radial_k3"),
                                        (2147483652, "pinhole_brown_t2"),
                                        (2147483653, "fisheye")]

    # Integer fields are JSON integers.
    for item in views:
        data = item["value"]["ptr_wrapper"]["data"]
        for key in ("width", "height", "id_view", "id_intrinsic", "id_pose"):
            assert type(data[key]) is int, key
        assert data["id_view"] == item["key"]
    by_view = {item["key"]: item["value"]["ptr_wrapper"]["data"] for item in views}
    assert (by_view[0]["local_path"], by_view[0]["filename"]) == ("a", "img0.jpg")
    assert (by_view[6]["id_intrinsic"], by_view[6]["id_pose"]) == (4294967295, 4294967295)
    assert (by_view[6]["width"], by_view[6]["height"]) == (4000, 3000)
    for item in intrinsics:
        data = item["value"]["ptr_wrapper"]["data"]
        assert type(data["width"]) is int and type(data["height"]) is int
    k3 = intrinsics[2]["value"]["ptr_wrapper"]["data"]
    assert k3["focal_length"] == 1100.0 and k3["disto_k3"] == [-0.21, 0.09, -0.02]
    assert k3["principal_point"] == [699.75, 480.25]  # OpenMVG pixel convention (-0.5)
    assert len(intrinsics[3]["value"]["ptr_wrapper"]["data"]["disto_t2"]) == 5
    assert len(intrinsics[4]["value"]["ptr_wrapper"]["data"]["fisheye"]) == 4

    # Extrinsics: row-major world->camera rotation + centre; every pose used by a view;
    # the rig pose 3 (views 3 and 4) written once.
    extrinsics = {item["key"]: item["value"] for item in document["extrinsics"]}
    assert sorted(extrinsics) == [0, 1, 2, 3, 5]
    assert set(extrinsics) <= {data["id_pose"] for data in by_view.values()}
    for pose_id in extrinsics:
        np.testing.assert_array_equal(extrinsics[pose_id]["rotation"],
                                      scene.poses[pose_id].R_cam_from_world)
        np.testing.assert_array_equal(extrinsics[pose_id]["center"], scene.poses[pose_id].center)

    # Structure: sorted keys, X, observations keyed by view with id_feat (int) and x (-0.5).
    structure = document["structure"]
    assert [item["key"] for item in structure] == [3, 7, 11]
    landmark = structure[1]["value"]
    np.testing.assert_array_equal(landmark["X"], scene.structure.points[0])
    assert [(o["key"], o["value"]["id_feat"]) for o in landmark["observations"]] == [(0, 4), (1, 9)]
    assert all(type(o["value"]["id_feat"]) is int for o in landmark["observations"])
    np.testing.assert_allclose(landmark["observations"][0]["value"]["x"], [511.2, -0.2],
                               atol=1e-12)
    assert [o["key"] for o in structure[2]["value"]["observations"]] == [0, 1, 5]

    openmvg.write_sfm_data(path, scene, include_structure=False)
    assert json.loads(path.read_text())["structure"] == []


def test_structure_pixels_fall_back_to_keypoints_then_projection(tmp_path):
    scene = _synthetic_scene(np.random.default_rng(3))
    scene.structure.observation_pixels = None
    scene.keypoints[0] = np.arange(40, dtype=float).reshape(20, 2) + 0.5
    pose, intrinsic = scene.poses[1], scene.intrinsics[1]
    point = pose.center + pose.R_cam_from_world.T @ np.array([0.1, -0.2, 3.0])
    scene.structure.points[0] = point
    document = openmvg.sfm_data_document(scene)
    observations = {o["key"]: o["value"]["x"] for o in document["structure"][1]["value"]
                    ["observations"]}
    np.testing.assert_allclose(observations[0], [8.0, 9.0])  # keypoint 4 of view 0, -0.5
    projected = openmvg.distort_project(intrinsic, np.array([[0.1 / 3.0, -0.2 / 3.0]]))[0]
    np.testing.assert_allclose(observations[1], projected - 0.5, atol=1e-9)


# =============================================================================== camera models

@pytest.mark.parametrize("model", list(MODELS))
def test_distort_undistort_round_trip(model):
    intrinsic = Intrinsics(0, model, 1280, 960, np.array(MODELS[model]))
    rng = np.random.default_rng(4)
    normalized = rng.uniform(-0.6, 0.6, size=(500, 2))
    normalized[0] = 0.0  # the centre is a special case in every model
    pixels = openmvg.distort_project(intrinsic, normalized)
    np.testing.assert_allclose(openmvg.undistort_normalize(intrinsic, pixels), normalized,
                               rtol=0, atol=1e-9)
    pixels_again = openmvg.distort_project(intrinsic,
                                           openmvg.undistort_normalize(intrinsic, pixels))
    np.testing.assert_allclose(pixels_again, pixels, rtol=0, atol=1e-9 * MODELS[model][0])
    if model != "pinhole":  # distortion really acts
        assert np.abs(pixels - (normalized * MODELS[model][0] + MODELS[model][1:3])).max() > 1.0


@pytest.mark.parametrize("model", ["pinhole_radial_k3", "pinhole_brown_t2", "fisheye"])
def test_forward_model_matches_opencv(model):
    """OpenMVG's radial/Brown are OpenCV's (k1, k2, p1=t1, p2=t2, k3); fisheye is OpenCV's."""
    f, cx, cy, *k = MODELS[model]
    intrinsic = Intrinsics(0, model, 1280, 960, np.array(MODELS[model]))
    normalized = np.random.default_rng(5).uniform(-0.5, 0.5, size=(50, 2))
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    if model == "fisheye":
        expected = cv2.fisheye.distortPoints(normalized[None], K, np.array(k))[0]
    else:
        dist = np.array([k[0], k[1], 0, 0, k[2]]) if model == "pinhole_radial_k3" else \
            np.array([k[0], k[1], k[3], k[4], k[2]])
        points = np.c_[normalized, np.ones(len(normalized))]
        expected = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0][:, 0]
    np.testing.assert_allclose(openmvg.distort_project(intrinsic, normalized), expected,
                               rtol=0, atol=1e-7)


def test_unknown_model_rejected():
    with pytest.raises(InputError, match="spherical"):
        openmvg.undistort_normalize(Intrinsics(0, "spherical", 10, 10, np.zeros(0)),
                                    np.zeros((1, 2)))


# ========================================================================= .feat, matches, pairs

def test_feat_round_trip(tmp_path):
    rng = np.random.default_rng(6)
    pixels = rng.uniform(0, 1536, size=(1000, 2))
    pixels[:3] = [[0.5, 0.5], [511.7, 0.3], [1023.9, 1.2]]
    path = tmp_path / "img.feat"
    openmvg.write_features(path, pixels)
    lines = path.read_text().splitlines()
    assert len(lines) == 1000 and lines[0] == "0 0 1 0"
    read = openmvg.read_features(path)
    # 9 significant digits: below the float32 resolution OpenMVG keeps (6e-5 px at 1024).
    np.testing.assert_allclose(read, pixels, rtol=0, atol=6e-6)
    again = tmp_path / "again.feat"
    openmvg.write_features(again, read)
    assert again.read_bytes() == path.read_bytes()
    table = openmvg.read_feature_table(CUT_PROJECT / "0000.feat")
    assert table.shape == (42, 4) and np.all(table[:, 2] > 0)


def test_feat_tolerates_tabs_blank_lines_and_no_final_newline(tmp_path):
    path = tmp_path / "x.feat"
    path.write_text("1 2 3 4\n\n5\t6  7 8\r\n9 10 11 12")
    np.testing.assert_array_equal(openmvg.read_features(path),
                                  [[1.5, 2.5], [5.5, 6.5], [9.5, 10.5]])


@pytest.mark.parametrize("suffix", [".txt", ".bin"])
def test_matches_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(7)
    matches = {(0, 3): rng.integers(0, 5000, size=(40, 2)), (1, 2): np.zeros((0, 2), int),
               (2, 9): rng.integers(0, 5000, size=(3, 2))}
    path = tmp_path / f"matches.e{suffix}"
    openmvg.write_matches(path, matches)
    read = openmvg.read_matches(path)
    assert list(read) == [(0, 3), (1, 2), (2, 9)]
    for key, value in matches.items():
        np.testing.assert_array_equal(read[key], value)
    again = tmp_path / f"again{suffix}"
    openmvg.write_matches(again, {k: PairMatches(k[0], k[1], v) for k, v in read.items()})
    assert again.read_bytes() == path.read_bytes()
    if suffix == ".txt":
        assert path.read_text().startswith("0 3\n40\n")


def test_matches_reversed_pair_is_swapped(tmp_path):
    path = tmp_path / "m.txt"
    path.write_text("5 2\n2\n10 20\n11 21\n")
    read = openmvg.read_matches(path)
    np.testing.assert_array_equal(read[(2, 5)], [[20, 10], [21, 11]])


def test_pairs_read_write(tmp_path):
    path = tmp_path / "pairs.bin"
    path.write_text("0 1 2 3\n2 1\n\n4 3\n")
    assert openmvg.read_pairs(path) == [(0, 1), (0, 2), (0, 3), (1, 2), (3, 4)]
    openmvg.write_pairs(path, [(3, 1), (0, 2), (1, 3)])
    assert path.read_text() == "0 2\n1 3\n"
    path.write_text("0 5\n")
    with pytest.raises(InputError, match="pairs.bin"):
        openmvg.read_pairs(path, num_views=5)
    path.write_text("2 2\n")
    with pytest.raises(InputError, match="invalid pair"):
        openmvg.read_pairs(path)


# =============================================================================== projects

def test_write_project_then_read_project(tmp_path):
    scene = openmvg.read_project(CUT_PROJECT / "sfm_data.json")
    scene.pairs[(0, 7)] = PairMatches(0, 7, np.array([[1, 2], [3, 4]]), verified=False)
    out = tmp_path / "project"
    openmvg.write_project(out, scene)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{i:04d}.feat" for i in range(8)] + ["sfm_data.json", "image_describer.json",
                                               "matches.e.bin", "matches.putative.bin"])
    describer = json.loads((out / "image_describer.json").read_text())
    assert describer["regions_type"]["polymorphic_name"] == "SIFT_Regions"
    back = openmvg.read_project(out / "sfm_data.json")
    for view_id in scene.views:
        np.testing.assert_allclose(back.keypoints[view_id], scene.keypoints[view_id], atol=1e-9)
    assert set(back.pairs) == set(scene.pairs) - {(0, 7)}
    putative = openmvg.read_matches(out / "matches.putative.bin")
    np.testing.assert_array_equal(putative[(0, 7)], [[1, 2], [3, 4]])
    # Writing into an existing folder replaces our files and keeps the others.
    (out / "keep.txt").write_text("x")
    openmvg.write_project(out, scene)
    assert (out / "keep.txt").read_text() == "x"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# =============================================================================== bad inputs

def _sfm_data_with(tmp_path: Path, edit) -> Path:
    document = json.loads((FIXTURES / "sfm_data.json").read_text())
    edit(document)
    path = tmp_path / "sfm_data.json"
    path.write_text(json.dumps(document))
    return path


def test_missing_files(tmp_path):
    with pytest.raises(InputError, match="nope.json: file not found"):
        openmvg.read_sfm_data(tmp_path / "nope.json")
    with pytest.raises(InputError, match="0000.feat: file not found"):
        openmvg.read_project(FIXTURES / "sfm_data.json", matches_dir=tmp_path)
    with pytest.raises(InputError, match="m.bin: file not found"):
        openmvg.read_matches(tmp_path / "m.bin")


def test_malformed_json(tmp_path):
    path = tmp_path / "sfm_data.json"
    path.write_text('{"sfm_data_version": "0.3", "views": [')
    with pytest.raises(InputError, match=r"sfm_data.json: malformed JSON"):
        openmvg.read_sfm_data(path)


def test_field_of_wrong_type(tmp_path):
    def string_width(document):
        document["views"][0]["value"]["ptr_wrapper"]["data"]["width"] = "1536"

    def float_width(document):  # cereal's GetUint() rejects 1536.0 too
        document["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["width"] = 1536.0

    def text_focal(document):
        document["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["focal_length"] = "f"

    with pytest.raises(InputError, match=r"sfm_data.json: views\[key=7\].*width"):
        openmvg.read_sfm_data(_sfm_data_with(tmp_path, string_width))
    with pytest.raises(InputError, match=r"sfm_data.json: intrinsics\[key=0\].*width"):
        openmvg.read_sfm_data(_sfm_data_with(tmp_path, float_width))
    with pytest.raises(InputError, match=r"focal_length: expected a number"):
        openmvg.read_sfm_data(_sfm_data_with(tmp_path, text_focal))
    with pytest.raises(InputError, match=r"sfm_data.json: views: expected an array"):
        openmvg.read_sfm_data(_sfm_data_with(tmp_path, lambda d: d.update(views={})))


def test_unknown_intrinsic_type(tmp_path):
    def spherical(document):
        document["intrinsics"][0]["value"]["polymorphic_name"] = "spherical"

    with pytest.raises(InputError, match=r"sfm_data.json: .*unsupported intrinsic type "
                                         r"'spherical'"):
        openmvg.read_sfm_data(_sfm_data_with(tmp_path, spherical))


def test_feat_line_with_wrong_column_count(tmp_path):
    path = tmp_path / "0000.feat"
    path.write_text("1 2 3 4\n5 6 7\n8 9 10 11 12\n")
    with pytest.raises(InputError, match=r"0000.feat: line 2: 3 columns, expected 4"):
        openmvg.read_features(path)
    path.write_text("1 2 3 4\n5 6 x 8\n")
    with pytest.raises(InputError, match=r"0000.feat: .*non-numeric"):
        openmvg.read_features(path)


def test_truncated_matches_bin(tmp_path):
    payload = (FIXTURES / "cut_project" / "matches.e.bin").read_bytes()
    path = tmp_path / "matches.e.bin"
    for cut in (5, 20, len(payload) - 3):
        path.write_bytes(payload[:cut])
        with pytest.raises(InputError, match=r"matches.e.bin: .*truncated"):
            openmvg.read_matches(path)
    text_path = tmp_path / "matches.e.txt"
    text_path.write_text("0 1\n3\n1 2\n")
    with pytest.raises(InputError, match=r"matches.e.txt: .*truncated"):
        openmvg.read_matches(text_path)


def test_match_index_beyond_keypoints(tmp_path):
    for source in CUT_PROJECT.iterdir():
        shutil.copy(source, tmp_path / source.name)
    openmvg.write_matches(tmp_path / "matches.e.bin", {(0, 1): np.array([[0, 0], [42, 0]])})
    with pytest.raises(InputError, match=r"matches.e.bin: pair \(0, 1\): feature index 42"):
        openmvg.read_project(tmp_path / "sfm_data.json")


def test_radial_bisection_is_openmvgs_and_polish_stays_inside_its_bracket():
    k = np.array([-0.21, 0.09, -0.02])
    r2_distorted = np.array([1e-4, 0.01, 0.2, 0.5])
    bisection = openmvg.cameras._bisection_radius_solve(k, r2_distorted)
    polished = openmvg.cameras._newton_polish_radius(k, r2_distorted, bisection)
    # OpenMVG's bracket is 1e-10 wide on r^2: its midpoint is within 5e-11 of the root.
    assert np.all(np.abs(polished - bisection) <= 5e-11)
    residual = openmvg.cameras._radial_disto_functor(k, polished) - r2_distorted
    assert np.all(np.abs(residual) <= 4 * np.finfo(float).eps * r2_distorted)
    assert np.all(np.abs(openmvg.cameras._radial_disto_functor(k, bisection) - r2_distorted) > 0)


def _view_json(view_id: int, ptr_id: int, poly: dict) -> dict:
    return {"key": view_id, "value": {**poly, "ptr_wrapper": {"id": ptr_id, "data": {
        "local_path": "", "filename": f"{view_id}.jpg", "width": 640, "height": 480,
        "id_view": view_id, "id_intrinsic": 0, "id_pose": view_id}}}}


def test_reader_follows_cereal_polymorphic_tables(tmp_path):
    """ViewPriors named first take polymorphic id 1; the intrinsic type then gets 2 and its
    later uses carry only ``2`` (formats.md §1.2); a ptr id without the high bit refers back."""
    k3 = {"width": 640, "height": 480, "focal_length": 500, "principal_point": [319.5, 239.5],
          "disto_k3": [0.1, 0, 0]}
    document = {
        "sfm_data_version": "0.3", "root_path": "",
        "views": [
            _view_json(4, 2147483649, {"polymorphic_id": 2147483649,
                                       "polymorphic_name": "view_priors"}),
            _view_json(2, 2147483650, {"polymorphic_id": 1}),
            _view_json(3, 2147483651, {"polymorphic_id": 1073741824}),
        ],
        "intrinsics": [
            {"key": 0, "value": {"polymorphic_id": 2147483650,
                                 "polymorphic_name": "pinhole_radial_k3",
                                 "ptr_wrapper": {"id": 2147483652, "data": k3}}},
            {"key": 1, "value": {"polymorphic_id": 2, "ptr_wrapper": {
                "id": 2147483653, "data": {**k3, "focal_length": 600}}}},
            {"key": 5, "value": {"polymorphic_id": 2, "ptr_wrapper": {"id": 4}}},
        ],
        "extrinsics": [], "structure": [], "control_points": []}
    path = tmp_path / "sfm_data.json"
    path.write_text(json.dumps(document))
    scene = openmvg.read_sfm_data(path)
    assert sorted(scene.views) == [2, 3, 4] and scene.views[4].name == "4.jpg"
    assert [scene.intrinsics[i].model for i in (0, 1, 5)] == ["pinhole_radial_k3"] * 3
    np.testing.assert_array_equal(scene.intrinsics[1].params, [600, 320, 240, 0.1, 0, 0])
    np.testing.assert_array_equal(scene.intrinsics[5].params, scene.intrinsics[0].params)
    document["intrinsics"][1]["value"]["polymorphic_id"] = 3  # never named
    path.write_text(json.dumps(document))
    with pytest.raises(InputError, match=r"intrinsics\[key=1\].polymorphic_id"):
        openmvg.read_sfm_data(path)


def test_reader_accepts_version_0_2_views(tmp_path):
    document = json.loads((FIXTURES / "sfm_data.json").read_text())
    document["sfm_data_version"] = "0.2"
    for item in document["views"]:
        del item["value"]["polymorphic_id"]
    path = tmp_path / "sfm_data.json"
    path.write_text(json.dumps(document))
    assert len(openmvg.read_sfm_data(path).views) == 8


def test_fast_structure_text_equals_json_dumps():
    scene = _synthetic_scene(np.random.default_rng(8))
    structure = scene.structure
    structure.point_ids = np.append(structure.point_ids, 0)
    structure.points = np.vstack([structure.points, [1e-5, -0.0, 3e20]])
    structure.observations.append([])
    structure.observation_pixels.append(np.zeros((0, 2)))
    expected = json.dumps(openmvg.sfm_data_document(scene), indent=4, ensure_ascii=False)
    assert openmvg.sfm_data_bytes(scene) == expected.encode("utf-8")
    assert '"observations": []' in expected and "1e-05" in expected


def test_poses_only_read_equals_the_full_read_without_structure(tmp_path):
    path = tmp_path / "sfm_data.json"
    path.write_bytes(openmvg.sfm_data_bytes(_synthetic_scene(np.random.default_rng(5))))
    full = openmvg.read_sfm_data(path)
    poses = openmvg.read_sfm_data(path, poses_only=True)
    assert full.structure is not None and len(full.structure.points) > 0 and full.poses
    assert poses.structure is None
    assert poses.views == full.views and poses.intrinsics.keys() == full.intrinsics.keys()
    assert poses.poses.keys() == full.poses.keys()
    for view_id, pose in full.poses.items():
        np.testing.assert_array_equal(poses.poses[view_id].R_cam_from_world, pose.R_cam_from_world)
        np.testing.assert_array_equal(poses.poses[view_id].center, pose.center)
    for intrinsic_id, intrinsics in full.intrinsics.items():
        np.testing.assert_array_equal(poses.intrinsics[intrinsic_id].params, intrinsics.params)
