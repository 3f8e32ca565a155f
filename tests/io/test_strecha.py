"""io.strecha on the fixtures: file layout, R transposition, names, GT dispatch."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import colmap, openmvg
from rotonly_cli.io.detect import read_ground_truth
from rotonly_cli.io.strecha import read_camera_file, read_strecha_dir

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES
HJ = FIXTURES / "herzjesu_p8"


def test_reads_names_ids_intrinsics_and_transposes_R() -> None:
    scene = read_strecha_dir(HJ)
    assert [scene.views[k].name for k in sorted(scene.views)] == [f"{k:04d}.jpg" for k in range(8)]
    assert all(view.pose_id == view.id == view.intrinsics_id for view in scene.views.values())
    # 0000.jpg.camera: K row 0 = 1379.74 0 760.095, R row 0 = -0.0552 0.132982 0.98958,
    # C = -6.71999 -14.2551 0.279539, then 1536 1024
    intrinsic = scene.intrinsics[0]
    assert (intrinsic.model, intrinsic.width, intrinsic.height) == ("PINHOLE", 1536, 1024)
    np.testing.assert_allclose(intrinsic.params, [1379.74, 1382.08, 760.595, 503.655])  # pp + 0.5
    pose = scene.poses[0]
    np.testing.assert_array_equal(pose.R_cam_from_world[:, 0], [-0.0552, 0.132982, 0.98958])  # file row 0
    np.testing.assert_array_equal(pose.R_cam_from_world[0], [-0.0552, 0.998433, -0.00921322])  # file column 0
    np.testing.assert_array_equal(pose.center, [-6.71999, -14.2551, 0.279539])
    K, R_file, C, size = read_camera_file(HJ / "gt_dense_cameras" / "0000.jpg.camera")
    np.testing.assert_array_equal(pose.R_cam_from_world, R_file.T)
    assert size == (1536, 1024) and K[2, 2] == 1.0


def test_gt_reprojects_database_matches() -> None:
    """Triangulating the fixture's inlier matches with the GT cameras (matched by name) gives
    sub-pixel reprojection and positive depths; an untransposed R would give neither."""
    gt = read_strecha_dir(HJ)
    database = colmap.read_database(HJ / "database.db")
    by_name = {view.name: view_id for view_id, view in gt.views.items()}
    i, j = 1, 2  # images 0001.jpg and 0000.jpg in the database
    pair = database.pairs[(i, j)]
    pose_i, pose_j = gt.poses[by_name[database.views[i].name]], gt.poses[by_name[database.views[j].name]]
    fx, fy, cx, cy = gt.intrinsics[0].params

    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])  # COLMAP pixel convention

    def projection(R: np.ndarray, center: np.ndarray) -> np.ndarray:
        return K @ np.c_[R, -R @ center]  # x = K R (X - c)

    def errors(R_i: np.ndarray, R_j: np.ndarray) -> tuple[float, float]:
        P_i, P_j = projection(R_i, pose_i.center), projection(R_j, pose_j.center)
        u_i = database.keypoints[i][pair.matches[:, 0]]
        u_j = database.keypoints[j][pair.matches[:, 1]]
        # linear (DLT) triangulation, batched over matches
        A = np.stack([u_i[:, :1] * P_i[2] - P_i[0], u_i[:, 1:] * P_i[2] - P_i[1],
                      u_j[:, :1] * P_j[2] - P_j[0], u_j[:, 1:] * P_j[2] - P_j[1]], axis=1)
        X = np.linalg.svd(A)[2][:, -1]
        X = X[:, :3] / X[:, 3:]
        reprojection, in_front = [], []
        for P, u in ((P_i, u_i), (P_j, u_j)):
            x = X @ P[:, :3].T + P[:, 3]
            reprojection.append(np.linalg.norm(x[:, :2] / x[:, 2:] - u, axis=1))
            in_front.append(x[:, 2] > 0)
        return float(np.median(np.concatenate(reprojection))), float(np.mean(in_front[0] & in_front[1]))

    median_px, front = errors(pose_i.R_cam_from_world, pose_j.R_cam_from_world)
    assert median_px < 0.3 and front > 0.99
    median_px, front = errors(pose_i.R_cam_from_world.T, pose_j.R_cam_from_world.T)  # file R as is
    assert median_px > 5.0 or front < 0.5


def test_read_ground_truth_dispatch(tmp_path: Path) -> None:
    from_scene_dir = read_ground_truth(HJ)
    from_camera_dir = read_ground_truth(HJ / "gt_dense_cameras")
    assert from_scene_dir.source == from_camera_dir.source == "strecha"
    for view_id, pose in from_scene_dir.poses.items():
        np.testing.assert_array_equal(from_camera_dir.poses[view_id].R_cam_from_world, pose.R_cam_from_world)
    # as an OpenMVG sfm_data.json (0-based ids kept) ...
    openmvg.write_sfm_data(tmp_path / "gt.json", colmap.to_openmvg_scene(from_scene_dir))
    from_json = read_ground_truth(tmp_path / "gt.json")
    assert {v.name for v in from_json.views.values()} == {v.name for v in from_scene_dir.views.values()}
    np.testing.assert_allclose(from_json.poses[3].center, from_scene_dir.poses[3].center, atol=1e-12)
    # ... and as a COLMAP model (ids + 1); Strecha R is not exactly orthonormal, so the model
    # (quaternions) holds its nearest rotation: compare centres and names
    colmap.write_model(tmp_path / "model", from_scene_dir)
    from_model = read_ground_truth(tmp_path / "model")
    assert sorted(from_model.views) == list(range(1, 9))
    for view_id, pose in from_scene_dir.poses.items():
        assert from_model.views[view_id + 1].name == from_scene_dir.views[view_id].name
        np.testing.assert_allclose(from_model.poses[view_id + 1].center, pose.center, atol=1e-4)


def test_folder_without_camera_files(tmp_path: Path) -> None:
    (tmp_path / "gt_dense_cameras").mkdir()
    with pytest.raises(InputError, match=r"no \.camera files") as info:
        read_ground_truth(tmp_path)
    assert info.value.path == str(tmp_path / "gt_dense_cameras")
    with pytest.raises(InputError, match="no such"):
        read_ground_truth(tmp_path / "missing")


def test_truncated_camera_file(tmp_path: Path) -> None:
    shutil.copytree(HJ / "gt_dense_cameras", tmp_path / "gt_dense_cameras")
    broken = tmp_path / "gt_dense_cameras" / "0003.jpg.camera"
    broken.write_text(" ".join(broken.read_text().split()[:20]))
    with pytest.raises(InputError, match="20 numbers") as info:
        read_strecha_dir(tmp_path)
    assert info.value.path == str(broken)
