"""`rotonly convert` and the stage behind it, on the fixtures only."""

from __future__ import annotations

import hashlib
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from rotonly_cli.cli import main
from rotonly_cli.io import colmap, openmvg
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, View

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES
HJ = FIXTURES / "herzjesu_p8"


def _tree_digest(path: Path) -> dict[str, str]:
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path.parent)): hashlib.md5(p.read_bytes()).hexdigest() for p in files}


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    captured = capsys.readouterr()
    return int(exit_info.value.code or 0), captured.out, captured.err


# .feat files hold 17 significant digits (io.openmvg.write_features): the 1e-9 bound
# on normalized coordinates holds (the remaining difference is the camera-model conversion)
FEAT_TEXT_TOLERANCE = 1e-9


def _assert_same_observations(db_scene, omvg_scene) -> None:
    """Views matched by name: identical matches, normalized coordinates equal up to the
    precision of the .feat text."""
    omvg_id = {view.name: view_id for view_id, view in omvg_scene.views.items()}
    id_map = {view_id: omvg_id[view.name] for view_id, view in db_scene.views.items()}
    for view_id in db_scene.views:
        np.testing.assert_allclose(omvg_scene.normalized[id_map[view_id]], db_scene.normalized[view_id],
                                   rtol=0, atol=FEAT_TEXT_TOLERANCE)
    assert len(omvg_scene.pairs) == len(db_scene.pairs)
    for (i, j), pair in db_scene.pairs.items():
        other = omvg_scene.pairs[(id_map[i], id_map[j])]  # the id shift is monotone: same orientation
        np.testing.assert_array_equal(other.matches, pair.matches)
        assert other.verified and other.config == "E"


def test_database_to_openmvg_project_and_back(tmp_path: Path, capsys) -> None:
    before = _tree_digest(HJ / "database.db")
    code, _, err = _run(["convert", str(HJ / "database.db"), "-o", str(tmp_path / "omvg")], capsys)
    assert code == 0, err
    assert _tree_digest(HJ / "database.db") == before
    db_scene = colmap.read_database(HJ / "database.db")
    omvg_scene = openmvg.read_project(tmp_path / "omvg" / "sfm_data.json")
    assert sorted(omvg_scene.views) == list(range(8))  # COLMAP ids 1..8 -> OpenMVG 0..7
    # PINHOLE fx != fy has no OpenMVG twin: one focal (fx + fy) / 2, keypoints re-rendered
    fx, fy, cx, cy = db_scene.intrinsics[1].params
    assert omvg_scene.intrinsics[0].model == "pinhole"
    np.testing.assert_allclose(omvg_scene.intrinsics[0].params, [(fx + fy) / 2, cx, cy], rtol=0, atol=1e-12)
    _assert_same_observations(db_scene, omvg_scene)
    # ... and OpenMVG -> database again: same matches, normalized within float32 keypoint precision
    code, _, err = _run(["convert", str(tmp_path / "omvg" / "sfm_data.json"), "-o", str(tmp_path / "back.db")], capsys)
    assert code == 0, err
    back = colmap.read_database(tmp_path / "back.db")
    assert back.views == db_scene.views and back.pairs.keys() == db_scene.pairs.keys()
    for key, pair in db_scene.pairs.items():
        np.testing.assert_array_equal(back.pairs[key].matches, pair.matches)
    for view_id in db_scene.views:
        np.testing.assert_allclose(back.normalized[view_id], db_scene.normalized[view_id], rtol=0, atol=5e-8)


def test_committed_openmvg_fixture_matches_database() -> None:
    _assert_same_observations(colmap.read_database(HJ / "database.db"),
                              openmvg.read_project(HJ / "openmvg" / "sfm_data.json"))


def test_pixel_centre_shift_only_at_the_openmvg_boundary(tmp_path: Path, capsys) -> None:
    """An exactly representable camera keeps its keypoints: .feat = DB keypoint - 0.5 and
    principal point - 0.5; both sides give the same normalized coordinates."""
    keypoints = np.array([[0.5, 0.5], [100.25, 30.75], [639.5, 479.5]])
    scene = SfMScene(views={1: View(1, "a.png", 1), 2: View(2, "b.png", 1)},
                     intrinsics={1: Intrinsics(1, "SIMPLE_RADIAL", 640, 480, np.array([500.0, 320.0, 240.0, 0.01]))},
                     keypoints={1: keypoints, 2: keypoints[::-1].copy()},
                     pairs={(1, 2): PairMatches(1, 2, np.array([[0, 2], [1, 1]]), config="CALIBRATED")})
    colmap.write_database(tmp_path / "s.db", scene)
    code, _, err = _run(["convert", str(tmp_path / "s.db"), "-o", str(tmp_path / "omvg")], capsys)
    assert code == 0, err
    feat = np.loadtxt(tmp_path / "omvg" / "a.feat")
    np.testing.assert_array_equal(feat[:, :2], keypoints - 0.5)
    omvg_scene = openmvg.read_project(tmp_path / "omvg" / "sfm_data.json")
    assert omvg_scene.intrinsics[0].model == "pinhole_radial_k1"
    sfm_data = (tmp_path / "omvg" / "sfm_data.json").read_text()
    assert '"principal_point": [\n' in sfm_data and "319.5" in sfm_data and "239.5" in sfm_data
    db_scene = colmap.read_database(tmp_path / "s.db")
    np.testing.assert_allclose(omvg_scene.normalized[0], db_scene.normalized[1], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(omvg_scene.keypoints[0], keypoints)  # back in COLMAP convention


def test_openmvg_project_to_database_counts(tmp_path: Path, capsys) -> None:
    before = _tree_digest(HJ / "openmvg")
    code, _, err = _run(["convert", str(HJ / "openmvg" / "sfm_data.json"), "-o", str(tmp_path / "hj.db")], capsys)
    assert code == 0, err
    assert _tree_digest(HJ / "openmvg") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hj.db"]
    database = pycolmap.Database.open(str(tmp_path / "hj.db"))
    try:
        assert database.num_images() == 8 and database.num_cameras() == 1
        assert database.num_keypoints() == 23844
        assert database.num_verified_image_pairs() == 28 and database.num_inlier_matches() == 19109
        assert database.read_camera(1).model.name == "SIMPLE_PINHOLE"
        assert {image.name for image in database.read_all_images()} == {f"{k:04d}.jpg" for k in range(8)}
    finally:
        database.close()


def _posed_openmvg_scene() -> SfMScene:
    rng = np.random.default_rng(11)
    scene = SfMScene(intrinsics={0: Intrinsics(0, "pinhole_radial_k3", 800, 600,
                                               np.array([700.0, 400.5, 300.5, -0.05, 0.01, 0.0]))})
    for view_id in range(4):
        scene.views[view_id] = View(view_id, f"v{view_id}.jpg", 0, pose_id=view_id)
        scene.poses[view_id] = Pose(Rotation.random(random_state=view_id).as_matrix(), rng.normal(size=3))
    return scene


def test_sfm_data_to_model_and_back(tmp_path: Path, capsys) -> None:
    scene = _posed_openmvg_scene()
    openmvg.write_sfm_data(tmp_path / "sfm_data.json", scene)
    code, _, err = _run(["convert", str(tmp_path / "sfm_data.json"), "-o", str(tmp_path / "model")], capsys)
    assert code == 0, err
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "model"))
    assert reconstruction.num_reg_images() == 4 and reconstruction.cameras[1].model.name == "RADIAL"
    code, _, err = _run(["convert", str(tmp_path / "model"), "-o", str(tmp_path / "again.json")], capsys)
    assert code == 0, err
    again = openmvg.read_sfm_data(tmp_path / "again.json")
    assert sorted(again.poses) == [0, 1, 2, 3]
    for view_id, pose in scene.poses.items():
        np.testing.assert_allclose(again.poses[view_id].R_cam_from_world, pose.R_cam_from_world, atol=1e-12)
        np.testing.assert_allclose(again.poses[view_id].center, pose.center, atol=1e-12)
    assert again.intrinsics[0].model == "pinhole_radial_k3"
    np.testing.assert_allclose(again.intrinsics[0].params, scene.intrinsics[0].params, atol=1e-12)


# ---------------------------------------------------------------------------- bad inputs

def _assert_rejected(code: int, err: str, named: Path, out_parent: Path, before: dict) -> None:
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(named) in lines[0] and lines[0].startswith("error: ")
    assert "Traceback" not in err
    assert sorted(p.name for p in out_parent.iterdir()) == sorted(before)


def test_missing_input(tmp_path: Path, capsys) -> None:
    missing = tmp_path / "nope.db"
    code, _, err = _run(["convert", str(missing), "-o", str(tmp_path / "out")], capsys)
    _assert_rejected(code, err, missing, tmp_path, {})


def test_not_sqlite(tmp_path: Path, capsys) -> None:
    bogus = tmp_path / "bogus.db"
    bogus.write_bytes(b"this is not a database\n" * 10)
    digest = _tree_digest(bogus)
    code, _, err = _run(["convert", str(bogus), "-o", str(tmp_path / "out")], capsys)
    _assert_rejected(code, err, bogus, tmp_path, {"bogus.db": None})
    assert _tree_digest(bogus) == digest


def test_database_without_two_view_geometries(tmp_path: Path, capsys) -> None:
    database = tmp_path / "db.db"
    shutil.copyfile(HJ / "database.db", database)
    connection = sqlite3.connect(database)
    connection.execute("DROP TABLE two_view_geometries")
    connection.commit()
    connection.close()
    digest = _tree_digest(database)
    code, _, err = _run(["convert", str(database), "-o", str(tmp_path / "out")], capsys)
    _assert_rejected(code, err, database, tmp_path, {"db.db": None})
    assert "two_view_geometries" in err and _tree_digest(database) == digest


def test_unwritable_output(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where a folder is needed\n")
    output = blocker / "out.db"
    before = _tree_digest(HJ / "openmvg")
    code, _, err = _run(["convert", str(HJ / "openmvg" / "sfm_data.json"), "-o", str(output)], capsys)
    _assert_rejected(code, err, output, tmp_path, {"blocker": None})
    assert blocker.read_text() == "a file where a folder is needed\n"
    assert _tree_digest(HJ / "openmvg") == before


def test_sfm_data_without_poses_to_model(tmp_path: Path, capsys) -> None:
    code, _, err = _run(["convert", str(HJ / "openmvg" / "sfm_data.json"), "-o", str(tmp_path / "model")], capsys)
    _assert_rejected(code, err, HJ / "openmvg" / "sfm_data.json", tmp_path, {})
    assert "extrinsics" in err


def test_gt_folder_without_camera_files(tmp_path: Path, capsys) -> None:
    gt = tmp_path / "scene"
    (gt / "gt_dense_cameras").mkdir(parents=True)
    (gt / "gt_dense_cameras" / "README").write_text("no cameras here\n")
    estimate = tmp_path / "estimate.json"
    openmvg.write_sfm_data(estimate, _posed_openmvg_scene())
    digest = _tree_digest(estimate)
    report = tmp_path / "report"
    code, _, err = _run(["eval", "--gt", str(gt), str(estimate), "-o", str(report)], capsys)
    _assert_rejected(code, err, gt / "gt_dense_cameras", tmp_path, {"scene": None, "estimate.json": None})
    assert ".camera" in err and _tree_digest(estimate) == digest
