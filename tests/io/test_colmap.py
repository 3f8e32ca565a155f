"""io.colmap on the Strecha fixtures (data_fixtures/, made by scripts/fixtures/make_fixtures.py)."""

from __future__ import annotations

import hashlib
import os
import shutil
import sqlite3
import subprocess
from contextlib import closing
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from rotonly_cli.errors import InputError
from rotonly_cli.io import colmap, openmvg
from rotonly_cli.io.strecha import read_strecha_dir
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, Structure, View

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES
HJ = FIXTURES / "herzjesu_p8"


def _md5(path: Path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def hj_scene() -> SfMScene:
    return colmap.read_database(HJ / "database.db")


def test_read_database_counts_and_input_unchanged() -> None:
    before = _md5(HJ / "database.db")
    scene = colmap.read_database(HJ / "database.db")
    assert _md5(HJ / "database.db") == before  # pycolmap alone would rewrite bytes of it
    assert len(scene.views) == 8 and len(scene.pairs) == 28
    assert sum(len(p.matches) for p in scene.pairs.values()) == 19109
    assert sum(len(k) for k in scene.keypoints.values()) == 23844
    assert {p.config for p in scene.pairs.values()} == {"CALIBRATED", "UNCALIBRATED", "PLANAR"}
    assert sorted(v.name for v in scene.views.values()) == [f"{k:04d}.jpg" for k in range(8)]
    assert all(p.verified and p.i < p.j and (p.i, p.j) == key for key, p in scene.pairs.items())
    for pair in scene.pairs.values():
        np.testing.assert_allclose(pair.R_j_from_i @ pair.R_j_from_i.T, np.eye(3), atol=1e-12)
        assert abs(np.linalg.norm(pair.t_j_from_i) - 1.0) < 1e-9


def test_read_database_leaves_no_sidecars_next_to_a_wal_input(tmp_path: Path) -> None:
    """pycolmap writes WAL-mode databases; even a read-only sqlite open of one would create
    -wal/-shm files beside it. read_database must leave the folder as it was."""
    import sqlite3

    database = tmp_path / "wal.db"
    database.write_bytes((HJ / "database.db").read_bytes())
    connection = sqlite3.connect(database)
    assert connection.execute("PRAGMA journal_mode=WAL").fetchone()[0] == "wal"
    connection.close()
    before = {p.name: _md5(p) for p in tmp_path.iterdir()}
    assert len(colmap.read_database(database).pairs) == 28
    assert {p.name: _md5(p) for p in tmp_path.iterdir()} == before


def test_normalized_is_pinhole_inverse(hj_scene: SfMScene) -> None:
    fx, fy, cx, cy = hj_scene.intrinsics[1].params
    assert hj_scene.intrinsics[1].model == "PINHOLE"
    for view_id, keypoints in hj_scene.keypoints.items():
        expected = (keypoints - [cx, cy]) / [fx, fy]
        np.testing.assert_allclose(hj_scene.normalized[view_id], expected, rtol=0, atol=1e-12)


def test_pair_orientation_matches_ground_truth(hj_scene: SfMScene) -> None:
    """The stored R_j_from_i agrees with R_j R_i^T of the GT, and the inlier columns index
    (i, j): the GT epipolar residual is tiny in this order and large swapped."""
    gt = read_strecha_dir(HJ)
    gt_by_name = {v.name: gt.poses[k] for k, v in gt.views.items()}
    calibrated_errors_deg = []
    for (i, j), pair in hj_scene.pairs.items():
        pose_i, pose_j = gt_by_name[hj_scene.views[i].name], gt_by_name[hj_scene.views[j].name]
        R_gt = pose_j.R_cam_from_world @ pose_i.R_cam_from_world.T
        t_gt = pose_j.R_cam_from_world @ (pose_i.center - pose_j.center)
        if pair.config == "CALIBRATED":
            cos = (np.trace(pair.R_j_from_i.T @ R_gt) - 1) / 2
            calibrated_errors_deg.append(np.degrees(np.arccos(min(cos, 1.0))))
        essential = np.cross(np.eye(3), t_gt / np.linalg.norm(t_gt)) @ R_gt  # [t]x R
        x_i = np.c_[hj_scene.normalized[i][pair.matches[:, 0]], np.ones(len(pair.matches))]
        x_j = np.c_[hj_scene.normalized[j][pair.matches[:, 1]], np.ones(len(pair.matches))]
        residual = np.abs(np.einsum("ni,ij,nj->n", x_j, essential, x_i))
        swapped = np.abs(np.einsum("ni,ij,nj->n", x_i, essential, x_j))
        assert np.median(residual) < 1e-3 and np.median(swapped) > 10 * np.median(residual)
    # COLMAP's stored E-based poses of this scene: median 0.08 deg, worst 1.4 deg
    assert len(calibrated_errors_deg) == 23
    assert np.median(calibrated_errors_deg) < 0.2 and max(calibrated_errors_deg) < 2.0


def test_write_database_round_trip(tmp_path: Path, hj_scene: SfMScene) -> None:
    out = tmp_path / "copy.db"
    colmap.write_database(out, hj_scene)
    back = colmap.read_database(out)
    assert back.views == hj_scene.views and back.pairs.keys() == hj_scene.pairs.keys()
    for key, pair in hj_scene.pairs.items():
        np.testing.assert_array_equal(back.pairs[key].matches, pair.matches)
        assert back.pairs[key].config == pair.config
        np.testing.assert_allclose(back.pairs[key].R_j_from_i, pair.R_j_from_i, atol=1e-12)
        np.testing.assert_allclose(back.pairs[key].t_j_from_i, pair.t_j_from_i, atol=1e-12)
    for view_id in hj_scene.views:
        np.testing.assert_array_equal(back.keypoints[view_id], hj_scene.keypoints[view_id])
    assert list(tmp_path.iterdir()) == [out]  # no staging leftovers
    with closing(sqlite3.connect(str(out))) as connection:  # COLMAP 3.8's layout (COLMAP 3.8 reads it)
        tables = {name for (name,) in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        columns = [row[1] for row in connection.execute("PRAGMA table_info(images)")]
    assert tables == {"cameras", "images", "keypoints", "descriptors", "matches", "two_view_geometries",
                      "sqlite_sequence"}
    assert columns[:4] == ["image_id", "name", "camera_id", "prior_qw"]
    database = pycolmap.Database.open(str(out))
    try:  # pycolmap 4.x migrates it on opening
        assert database.num_images() == 8 and database.num_matched_image_pairs() == 28
    finally:
        database.close()


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP's command-line tool not installed")
def test_colmap_cli_maps_a_written_database(tmp_path: Path, hj_scene: SfMScene) -> None:
    """The installed COLMAP (Debian's 3.8 here) reads what write_database writes."""
    colmap.write_database(tmp_path / "database.db", hj_scene)
    (tmp_path / "images").mkdir()
    (tmp_path / "sparse").mkdir()
    subprocess.run(["colmap", "mapper", "--database_path", str(tmp_path / "database.db"), "--image_path",
                    str(tmp_path / "images"), "--output_path", str(tmp_path / "sparse")], check=True,
                   capture_output=True, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"}, timeout=600)
    model = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    assert model.num_reg_images() == 8


def _small_openmvg_scene() -> SfMScene:
    """0-based OpenMVG-like scene with one radial_k1 camera and unverified + verified pairs."""
    rng = np.random.default_rng(7)
    scene = SfMScene(source="openmvg")
    scene.intrinsics[0] = Intrinsics(0, "pinhole_radial_k1", 640, 480, np.array([500.0, 320.5, 240.5, -0.05]))
    for view_id in range(3):
        scene.views[view_id] = View(view_id, f"img{view_id}.jpg", 0)
        scene.keypoints[view_id] = rng.uniform([0, 0], [640, 480], size=(50, 2)).astype(np.float32).astype(float)
        scene.normalized[view_id] = openmvg.undistort_normalize(scene.intrinsics[0], scene.keypoints[view_id])
    R = Rotation.from_rotvec([0.0, 0.1, 0.02]).as_matrix()
    scene.pairs[(0, 1)] = PairMatches(0, 1, np.array([[0, 5], [3, 1], [49, 0]]), R, np.array([1.0, 0, 0]), "E")
    scene.pairs[(1, 2)] = PairMatches(1, 2, np.array([[2, 2], [7, 9]]), verified=False)
    return scene


def test_write_database_shifts_zero_based_ids(tmp_path: Path) -> None:
    scene = _small_openmvg_scene()
    colmap.write_database(tmp_path / "s.db", scene)
    back = colmap.read_database(tmp_path / "s.db")
    assert sorted(back.views) == [1, 2, 3] and back.views[1].name == "img0.jpg"
    assert back.intrinsics[1].model == "SIMPLE_RADIAL"
    np.testing.assert_array_equal(back.intrinsics[1].params, [500.0, 320.5, 240.5, -0.05])
    assert back.pairs[(1, 2)].verified and back.pairs[(1, 2)].config == "CALIBRATED"
    np.testing.assert_array_equal(back.pairs[(1, 2)].matches, scene.pairs[(0, 1)].matches)
    np.testing.assert_allclose(back.pairs[(1, 2)].R_j_from_i, scene.pairs[(0, 1)].R_j_from_i, atol=1e-12)
    assert not back.pairs[(2, 3)].verified
    np.testing.assert_array_equal(back.pairs[(2, 3)].matches, scene.pairs[(1, 2)].matches)
    # pycolmap's and OpenMVG's radial_k1 undistortion agree on the same keypoints
    for view_id in range(3):
        np.testing.assert_allclose(back.normalized[view_id + 1], scene.normalized[view_id], atol=1e-9)


def test_write_database_guesses_a_camera_per_image_size_for_views_without_one(tmp_path: Path) -> None:
    """Views whose OpenMVG intrinsic is undefined (listed without EXIF focal) get COLMAP's
    no-EXIF camera, one per image size (it gave them all one, sized as the first), marked as
    a guess; views with a camera keep theirs."""
    scene = SfMScene(intrinsics={0: Intrinsics(0, "pinhole", 640, 480, np.array([500.0, 320.5, 240.5]))})
    sizes = {0: (640, 480), 1: (640, 480), 2: (640, 480), 3: (480, 640)}
    for view_id, (width, height) in sizes.items():
        intrinsic = 0 if view_id == 0 else openmvg.UNDEFINED_INDEX
        scene.views[view_id] = View(view_id, f"img{view_id}.jpg", intrinsic, width=width, height=height)
        scene.keypoints[view_id] = np.zeros((0, 2))
    colmap.write_database(tmp_path / "g.db", scene)
    back = colmap.read_database(tmp_path / "g.db")
    cameras = [back.intrinsics[back.views[view_id + 1].intrinsics_id] for view_id in range(4)]
    assert cameras[0].prior_focal is not False and cameras[0].model == "SIMPLE_PINHOLE"
    assert back.views[2].intrinsics_id == back.views[3].intrinsics_id != back.views[4].intrinsics_id
    assert cameras[1].prior_focal is False and cameras[1].model == "SIMPLE_RADIAL"
    np.testing.assert_allclose(cameras[1].params, [768.0, 320.0, 240.0, 0.0])
    np.testing.assert_allclose(cameras[3].params, [768.0, 240.0, 320.0, 0.0])
    assert len(back.intrinsics) == 3


@pytest.mark.parametrize("model, params", [
    ("pinhole", [800.0, 320.5, 240.5]),
    ("pinhole_radial_k1", [800.0, 320.5, 240.5, -0.1]),
    ("pinhole_radial_k3", [800.0, 320.5, 240.5, -0.1, 0.02, 0.0]),
    ("pinhole_radial_k3", [800.0, 320.5, 240.5, -0.1, 0.02, -0.003]),
    ("pinhole_brown_t2", [800.0, 320.5, 240.5, -0.1, 0.02, 0.0, 0.001, -0.002]),
    ("pinhole_brown_t2", [800.0, 320.5, 240.5, -0.1, 0.02, -0.003, 0.001, -0.002]),
    ("fisheye", [800.0, 320.5, 240.5, 0.01, -0.002, 0.001, -0.0005]),
])
def test_openmvg_models_map_to_same_colmap_projection(model: str, params: list[float]) -> None:
    openmvg_intrinsics = Intrinsics(3, model, 640, 480, np.array(params))
    colmap_intrinsics = colmap.to_colmap_intrinsics(openmvg_intrinsics)
    assert colmap_intrinsics.model != model and colmap_intrinsics.id == 3
    normalized = np.random.default_rng(1).uniform(-0.4, 0.4, size=(200, 2))
    expected = openmvg.distort_project(openmvg_intrinsics, normalized)
    camera = colmap.pycolmap_camera(colmap_intrinsics)
    projected = camera.img_from_cam(np.c_[normalized, np.ones(len(normalized))])
    np.testing.assert_allclose(projected, expected, rtol=0, atol=1e-9)
    # and back: an exactly representable COLMAP camera maps to an OpenMVG model again
    exact = colmap.cameras._exact_openmvg_intrinsics(colmap_intrinsics)
    assert exact is not None
    np.testing.assert_allclose(openmvg.distort_project(exact, normalized), expected, atol=1e-9)


def _posed_scene(hj_scene: SfMScene) -> SfMScene:
    rng = np.random.default_rng(3)
    scene = SfMScene(views=dict(hj_scene.views), intrinsics=dict(hj_scene.intrinsics),
                     keypoints=dict(hj_scene.keypoints))
    for view_id in list(scene.views)[:-1]:  # the last view stays unposed
        scene.poses[view_id] = Pose(Rotation.random(random_state=view_id).as_matrix(), rng.normal(size=3))
    tracks = [[(1, 3), (2, 5)], [(1, 4), (3, 7), (8, 1)], [(2, 2), (4, 4), (5, 9)], [(6, 1), (7, 1)]]
    scene.structure = Structure(np.arange(4), rng.normal(size=(4, 3)),
                                rng.integers(0, 256, (4, 3)).astype(np.uint8), tracks)
    return scene


@pytest.mark.parametrize("binary", [True, False])
def test_write_model_read_model(tmp_path: Path, hj_scene: SfMScene, binary: bool) -> None:
    scene = _posed_scene(hj_scene)
    out = tmp_path / "sparse"
    colmap.write_model(out, scene, binary=binary)
    ext = ".bin" if binary else ".txt"
    assert {p.name for p in out.iterdir()} == {f"{s}{ext}" for s in ("cameras", "images", "points3D", "rigs", "frames")}
    assert [p.name for p in tmp_path.iterdir()] == ["sparse"]
    back = colmap.read_model(out)
    assert set(back.poses) == set(scene.poses) and 8 not in back.views
    for view_id, pose in scene.poses.items():
        np.testing.assert_allclose(back.poses[view_id].R_cam_from_world, pose.R_cam_from_world, rtol=0, atol=1e-12)
        np.testing.assert_allclose(back.poses[view_id].center, pose.center, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(back.keypoints[view_id], scene.keypoints[view_id])
        assert back.views[view_id].name == scene.views[view_id].name
    np.testing.assert_allclose(back.structure.points, scene.structure.points, rtol=0, atol=1e-12 if binary else 1e-9)
    np.testing.assert_array_equal(back.structure.colors, scene.structure.colors)
    np.testing.assert_array_equal(back.structure.point_ids, [1, 2, 3, 4])  # COLMAP ids are > 0
    # the observation in unposed view 8 is dropped, the others kept in order
    assert back.structure.observations == [[(1, 3), (2, 5)], [(1, 4), (3, 7)],
                                           [(2, 2), (4, 4), (5, 9)], [(6, 1), (7, 1)]]
    assert back.intrinsics[1].model == "PINHOLE"


def test_write_model_from_openmvg_structure_without_keypoints(tmp_path: Path) -> None:
    """OpenMVG landmarks carry their pixels (``x``) but a sfm_data has no keypoints: the model
    gets those pixels as points2D and tracks pointing at them."""
    intrinsic = Intrinsics(0, "pinhole", 640, 480, np.array([500.0, 320.5, 240.5]))
    scene = SfMScene(views={0: View(0, "a.jpg", 0), 1: View(1, "b.jpg", 0)}, intrinsics={0: intrinsic},
                     poses={0: Pose(np.eye(3), np.zeros(3)), 1: Pose(np.eye(3), np.array([1.0, 0, 0]))})
    point = np.array([0.2, -0.1, 4.0])
    pixels = [openmvg.distort_project(intrinsic, ((point - pose.center)[:2] / point[2])[None])[0]
              for pose in scene.poses.values()]
    scene.structure = Structure(np.array([0]), point[None], None, [[(0, 17), (1, 230)]], [np.array(pixels)])
    colmap.write_model(tmp_path / "m", scene)
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "m"))
    assert reconstruction.compute_mean_reprojection_error() < 1e-9
    back = colmap.read_model(tmp_path / "m")
    assert back.intrinsics[1].model == "SIMPLE_PINHOLE" and sorted(back.views) == [1, 2]
    np.testing.assert_allclose(back.keypoints[1], pixels[0][None], atol=1e-12)


def test_read_model_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such folder"):
        colmap.read_model(tmp_path / "missing")
    (tmp_path / "cameras.bin").write_bytes(b"")
    with pytest.raises(InputError, match="not a COLMAP model"):
        colmap.read_model(tmp_path)


def test_rejected_pairs_are_dropped(tmp_path: Path) -> None:
    """A pair verified as DEGENERATE is neither a verified pair nor 'never verified'."""
    scene = _small_openmvg_scene()
    scene.pairs[(0, 2)] = PairMatches(0, 2, np.array([[1, 1], [2, 2]]), config="DEGENERATE")
    colmap.write_database(tmp_path / "r.db", scene)
    back = colmap.read_database(tmp_path / "r.db")
    assert sorted(back.pairs) == [(1, 2), (2, 3)]
    assert sorted(colmap.read_database(tmp_path / "r.db", include_unverified=False).pairs) == [(1, 2)]
