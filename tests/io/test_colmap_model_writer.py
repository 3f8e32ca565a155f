"""The numpy-assembled COLMAP sparse model gives the same bytes as building every 3D point
and track element as pycolmap objects (the previous writer, kept here as the reference)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import colmap
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View


def _reference_model(scene: SfMScene, out_dir: Path, binary: bool) -> None:
    """One pycolmap Point3D / TrackElement per point / observation (the old writer)."""
    reconstruction = pycolmap.Reconstruction()
    view_offset = colmap.id_offset(scene.views)
    camera_offset = colmap.id_offset(scene.intrinsics)
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = colmap.to_colmap_intrinsics(scene.intrinsics[intrinsic_id])
        reconstruction.add_camera_with_trivial_rig(colmap.pycolmap_camera(intrinsic, intrinsic_id + camera_offset))
    structure = scene.structure
    points2D: dict[int, list[np.ndarray]] = {}
    extra_index: dict[tuple[int, int], int] = {}
    posed = [view_id for view_id in sorted(scene.views) if view_id in scene.poses]
    for view_id in posed:
        keypoints = scene.keypoints.get(view_id)
        points2D[view_id] = [np.zeros((0, 2)) if keypoints is None else np.asarray(keypoints, float).reshape(-1, 2)]
    if structure is not None:
        for point_index, track in enumerate(structure.observations):
            for row, (view_id, feature) in enumerate(track):
                if view_id not in points2D:
                    continue
                if 0 <= feature < len(points2D[view_id][0]) or (view_id, feature) in extra_index:
                    continue
                pixel = colmap.model._observation_pixel(scene, point_index, row)
                extra_index[(view_id, feature)] = sum(len(p) for p in points2D[view_id])
                points2D[view_id].append(pixel.reshape(1, 2))
    for view_id in posed:
        view, pose = scene.views[view_id], scene.poses[view_id]
        R = np.asarray(pose.R_cam_from_world, dtype=np.float64)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ np.asarray(pose.center, float).reshape(3))
        image = pycolmap.Image(name=view.name, keypoints=np.concatenate(points2D[view_id]),
                               camera_id=view.intrinsics_id + camera_offset, image_id=view_id + view_offset)
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
    if structure is not None:
        point_offset = colmap.id_offset(np.asarray(structure.point_ids).tolist())
        colors = (np.zeros((len(structure.points), 3), np.uint8) if structure.colors is None
                  else np.asarray(structure.colors, dtype=np.uint8))
        for point_index, track in enumerate(structure.observations):
            elements = [pycolmap.TrackElement(view_id + view_offset, extra_index.get((view_id, feature), feature))
                        for view_id, feature in track if view_id in points2D]
            if elements:
                point3D = pycolmap.Point3D(xyz=np.asarray(structure.points[point_index], float),
                                           color=colors[point_index], track=pycolmap.Track(elements))
                reconstruction.add_point3D_with_id(int(structure.point_ids[point_index]) + point_offset, point3D)
    reconstruction.update_point_3d_errors()
    out_dir.mkdir()
    if binary:
        reconstruction.write_binary(str(out_dir))
    else:
        reconstruction.write_text(str(out_dir))


def _scene(rng: np.random.Generator, first_id: int, with_colors: bool, stored_pixels: bool) -> SfMScene:
    """8 views (two unposed, one posed without keypoints), two intrinsics, 300 points with
    shuffled ids, tracks in random view order, some observations beyond the keypoints or
    negative, some points seen only by unposed views."""
    scene = SfMScene()
    scene.intrinsics[first_id] = Intrinsics(first_id, "SIMPLE_RADIAL", 640, 480, np.array([500.0, 320.5, 240.5, 0.01]))
    scene.intrinsics[first_id + 1] = Intrinsics(first_id + 1, "PINHOLE", 800, 600, np.array([700.0, 710.0, 400, 300]))
    view_ids = [first_id + k for k in range(8)]
    for k, view_id in enumerate(view_ids):
        scene.views[view_id] = View(view_id, f"img{k}.jpg", first_id + k % 2)
        if k not in (2, 6):
            angle = 0.05 * k
            R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
            scene.poses[view_id] = Pose(R @ np.diag([1, 1, 1]), np.array([0.2 * k, 0.1, -6.0]))
        if k != 4:
            scene.keypoints[view_id] = rng.uniform(0, 600, (80, 2))
    observations, pixels = [], []
    for _ in range(300):
        views = rng.permutation(view_ids)[:rng.integers(1, 5)]
        observations.append([(int(v), int(k)) for v, k in zip(views, rng.permutation(90)[:len(views)])])
        pixels.append(rng.uniform(0, 600, (len(views), 2)))
    observations[5] = [(view_ids[4], -1), (view_ids[0], 85)]
    observations[6] = [(view_ids[2], 3), (view_ids[6], 4)]  # only unposed views: not in the model
    pixels[5], pixels[6] = rng.uniform(0, 600, (2, 2)), rng.uniform(0, 600, (2, 2))
    points = rng.normal(size=(300, 3))
    scene.structure = Structure(first_id + rng.permutation(1000)[:300], points,
                                rng.integers(0, 256, (300, 3)).astype(np.uint8) if with_colors else None,
                                observations, pixels if stored_pixels else None)
    # a keypoint used by the same point twice is allowed by pycolmap; keep the model valid:
    # no keypoint shared by two points
    used: set[tuple[int, int]] = set()
    for track in scene.structure.observations:
        track[:] = [obs for obs in track if obs not in used]
        used.update(track)
    return scene


@pytest.mark.parametrize("first_id,with_colors,stored_pixels,binary", [
    (1, True, True, True), (0, False, False, True), (1, False, True, False), (0, True, False, False)])
def test_sparse_model_bytes_equal_object_writer(tmp_path, first_id, with_colors, stored_pixels, binary):
    scene = _scene(np.random.default_rng(first_id + 2 * with_colors), first_id, with_colors, stored_pixels)
    _reference_model(scene, tmp_path / "reference", binary)
    colmap.write_model(tmp_path / "fast", scene, binary=binary)
    names = sorted(path.name for path in (tmp_path / "reference").iterdir())
    assert names == sorted(path.name for path in (tmp_path / "fast").iterdir())
    assert len(names) == 5
    for name in names:
        assert (tmp_path / "fast" / name).read_bytes() == (tmp_path / "reference" / name).read_bytes(), name
    model = pycolmap.Reconstruction(str(tmp_path / "fast"))
    assert model.num_reg_images() == 6
    # points seen only by unposed views are dropped
    expected = sum(any(view_id in scene.poses for view_id, _ in track) for track in scene.structure.observations)
    assert model.num_points3D() == expected and 150 < expected < 299
    assert np.isfinite(model.compute_mean_reprojection_error())
    assert not any(path.name.startswith(".") for path in tmp_path.iterdir())  # no work folders left


def test_sparse_model_without_structure_and_shared_keypoint(tmp_path):
    scene = _scene(np.random.default_rng(1), 1, True, True)
    scene.structure = None
    _reference_model(scene, tmp_path / "reference", True)
    colmap.write_model(tmp_path / "fast", scene)
    for name in ("cameras.bin", "images.bin", "points3D.bin", "frames.bin", "rigs.bin"):
        assert (tmp_path / "fast" / name).read_bytes() == (tmp_path / "reference" / name).read_bytes()
    scene = _scene(np.random.default_rng(1), 1, True, True)
    scene.structure.observations[1].append(scene.structure.observations[0][0])
    scene.structure.observation_pixels[1] = np.zeros((len(scene.structure.observations[1]), 2))
    view_id, feature = scene.structure.observations[0][0]
    with pytest.raises(InputError, match=f"keypoint {feature} of image {view_id} observed by two 3D points"):
        colmap.write_model(tmp_path / "bad", scene)
    assert not (tmp_path / "bad").exists()
    assert not any(path.name.startswith(".") for path in tmp_path.iterdir())


def test_sparse_model_without_posed_views(tmp_path):
    scene = _scene(np.random.default_rng(2), 1, True, True)
    scene.poses = {}
    _reference_model(scene, tmp_path / "reference", True)
    colmap.write_model(tmp_path / "fast", scene)
    for name in ("cameras.bin", "images.bin", "points3D.bin", "frames.bin", "rigs.bin"):
        assert (tmp_path / "fast" / name).read_bytes() == (tmp_path / "reference" / name).read_bytes()
    model = pycolmap.Reconstruction(str(tmp_path / "fast"))
    assert (model.num_images(), model.num_points3D(), model.num_cameras()) == (0, 0, 2)
