"""COLMAP sparse models (``cameras``, ``images``, ``points3D`` + 4.x ``rigs``, ``frames``;
formats.md §4.8): written with pycolmap, the points with numpy; read with pycolmap."""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.geometry.tracks import ranks_within
from rotonly_cli.io import atomic
from rotonly_cli.io.colmap.cameras import import_pycolmap, normalize_keypoints, pycolmap_camera, to_colmap_intrinsics
from rotonly_cli.io.colmap.database import id_offset
from rotonly_cli.io.colmap.model_check import check_model
from rotonly_cli.io.detect import is_colmap_model
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View

PathLike = str | os.PathLike
logger = logging.getLogger(__name__)


# ============================================================================ sparse model

def _reconstruction(pycolmap, scene: SfMScene, posed: list[int], extra_points2D: dict[int, np.ndarray]):
    """pycolmap.Reconstruction of the cameras and posed views of ``scene`` (points2D = the
    view's keypoints, then ``extra_points2D``), without 3D points."""
    reconstruction = pycolmap.Reconstruction()
    view_offset = id_offset(scene.views)
    camera_offset = id_offset(scene.intrinsics)
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = to_colmap_intrinsics(scene.intrinsics[intrinsic_id])
        reconstruction.add_camera_with_trivial_rig(
            pycolmap_camera(intrinsic, intrinsic_id + camera_offset))
    for view_id in posed:
        view = scene.views[view_id]
        if view.intrinsics_id not in scene.intrinsics:
            raise InputError("posed view without intrinsic", field=f"views[{view_id}]")
        pose = scene.poses[view_id]
        R = np.asarray(pose.R_cam_from_world, dtype=np.float64)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ np.asarray(
            pose.center, dtype=np.float64).reshape(3))
        keypoints = scene.keypoints.get(view_id)
        keypoints = (np.zeros((0, 2)) if keypoints is None
                     else np.asarray(keypoints, dtype=np.float64).reshape(-1, 2))
        image = pycolmap.Image(name=view.name, keypoints=np.concatenate([keypoints, extra_points2D[view_id]]),
                               camera_id=view.intrinsics_id + camera_offset,
                               image_id=view_id + view_offset)
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
    return reconstruction


@dataclass
class _ModelPoints:
    """3D points in COLMAP terms, tracks flattened: per point ``point3D_ids``, ``xyz``,
    ``colors``, ``track_lengths``; per track element ``image_ids``, ``point2D_indices``."""

    point3D_ids: np.ndarray
    xyz: np.ndarray
    colors: np.ndarray
    track_lengths: np.ndarray
    image_ids: np.ndarray
    point2D_indices: np.ndarray


def _model_points(scene: SfMScene, posed: list[int]) -> tuple[_ModelPoints, dict[int, np.ndarray]]:
    """Tracks of ``scene.structure`` restricted to posed views, and per posed view the extra
    points2D appended after its keypoints: observations whose keypoint index is out of
    range get the stored landmark pixel (or the projection), once per (view, index), in
    order of first use. Observations in unposed views are left out; points left without
    observations are not in the model."""
    extra_points2D = {view_id: np.zeros((0, 2)) for view_id in posed}
    structure = scene.structure
    if structure is None or not posed:  # no posed view: no 3D point is in the model
        empty = np.zeros(0, dtype=np.int64)
        return _ModelPoints(empty, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), empty, empty, empty), extra_points2D
    track_lengths, view_feature = structure.flat_observations()
    point_of_observation = np.repeat(np.arange(len(track_lengths)), track_lengths)
    posed_ids = np.asarray(posed, dtype=np.int64)
    num_keypoints = np.array([0 if scene.keypoints.get(view_id) is None else len(scene.keypoints[view_id])
                              for view_id in posed], dtype=np.int64)
    view_row = np.minimum(np.searchsorted(posed_ids, view_feature[:, 0]), len(posed) - 1)
    in_model = posed_ids[view_row] == view_feature[:, 0]
    features = view_feature[:, 1]
    point2D_indices = features.copy()
    is_extra = in_model & ((features < 0) | (features >= num_keypoints[view_row]))
    extra_observations = np.flatnonzero(is_extra)
    if extra_observations.size:  # rare (not in the pipeline): a Python loop is fine
        row_in_track = ranks_within(track_lengths)
        first_use: dict[tuple[int, int], int] = {}
        extras: dict[int, list[np.ndarray]] = {view_id: [] for view_id in posed}
        for observation in extra_observations.tolist():
            key = (int(view_feature[observation, 0]), int(features[observation]))
            if key not in first_use:
                view_id = key[0]
                first_use[key] = int(num_keypoints[view_row[observation]]) + len(extras[view_id])
                extras[view_id].append(_observation_pixel(scene, int(point_of_observation[observation]),
                                                          int(row_in_track[observation])).reshape(1, 2))
            point2D_indices[observation] = first_use[key]
        extra_points2D.update({view_id: np.concatenate(blocks) for view_id, blocks in extras.items() if blocks})

    in_model_per_point = np.bincount(point_of_observation[in_model], minlength=len(track_lengths))
    kept = in_model_per_point > 0
    point_ids = np.asarray(structure.point_ids, dtype=np.int64).reshape(-1)
    point_offset = id_offset(point_ids.tolist())
    colors = (np.zeros((len(track_lengths), 3), np.uint8) if structure.colors is None
              else np.asarray(structure.colors, dtype=np.uint8).reshape(-1, 3))
    view_offset = id_offset(scene.views)
    points = _ModelPoints(
        point3D_ids=point_ids[kept] + point_offset,
        xyz=np.asarray(structure.points, dtype=np.float64).reshape(-1, 3)[kept],
        colors=colors[kept], track_lengths=in_model_per_point[kept],
        image_ids=view_feature[in_model, 0] + view_offset, point2D_indices=point2D_indices[in_model])
    return points, extra_points2D


# points3D.bin record head (formats.md §4.8): id, xyz, rgb, error, track length
_POINT3D_HEAD = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"),
                          ("track_length", "<u8")])
_TRACK_ELEMENT = np.dtype([("image_id", "<u4"), ("point2D_idx", "<u4")])
_POINT2D = np.dtype([("xy", "<f8", 2), ("point3D_id", "<u8")])


def _points3D_bin(points: _ModelPoints) -> bytes:
    """points3D.bin with the given tracks and ERROR -1 (recomputed by pycolmap), assembled
    with numpy: one record = head, then track elements (formats.md §4.8)."""
    num_points = len(points.point3D_ids)
    heads = np.zeros(num_points, dtype=_POINT3D_HEAD)
    heads["id"], heads["xyz"], heads["rgb"] = points.point3D_ids, points.xyz, points.colors
    heads["error"], heads["track_length"] = -1.0, points.track_lengths
    elements = np.zeros(len(points.image_ids), dtype=_TRACK_ELEMENT)
    elements["image_id"], elements["point2D_idx"] = points.image_ids, points.point2D_indices
    head_size, element_size = _POINT3D_HEAD.itemsize, _TRACK_ELEMENT.itemsize
    record_start = 8 + head_size * np.arange(num_points) + element_size * (
        np.cumsum(points.track_lengths) - points.track_lengths)
    payload = np.zeros(8 + head_size * num_points + element_size * len(elements), dtype=np.uint8)
    payload[:8] = np.frombuffer(np.uint64(num_points).tobytes(), dtype=np.uint8)
    payload[(record_start[:, None] + np.arange(head_size)).reshape(-1)] = heads.view(np.uint8)
    element_start = (np.repeat(record_start + head_size, points.track_lengths)
                     + element_size * (np.arange(len(elements)) - np.repeat(
                         np.cumsum(points.track_lengths) - points.track_lengths, points.track_lengths)))
    payload[(element_start[:, None] + np.arange(element_size)).reshape(-1)] = elements.view(np.uint8)
    return payload.tobytes()


def _link_points2D(images_bin: bytes, points: _ModelPoints) -> bytes:
    """images.bin as pycolmap wrote it (no 3D points) with each track element's point2D
    pointing at its 3D point. A keypoint claimed by two points is an error (pycolmap's
    AddPoint3D refuses it too)."""
    payload = bytearray(images_bin)
    point3D_of_element = np.repeat(points.point3D_ids, points.track_lengths).astype(np.uint64)
    by_image = np.argsort(points.image_ids, kind="stable")  # track elements grouped by image
    sorted_image_ids = points.image_ids[by_image]
    (num_images,), offset = np.frombuffer(payload, "<u8", 1, 0), 8
    for _ in range(int(num_images)):
        image_id = int(np.frombuffer(payload, "<u4", 1, offset)[0])
        offset += 4 + 7 * 8 + 4  # id, qw qx qy qz tx ty tz, camera id
        offset = payload.index(b"\0", offset) + 1  # NUL-terminated name
        num_points2D = int(np.frombuffer(payload, "<u8", 1, offset)[0])
        offset += 8
        points2D = np.frombuffer(payload, _POINT2D, num_points2D, offset)  # a view: writes go to payload
        mine = by_image[np.searchsorted(sorted_image_ids, image_id, "left"):
                        np.searchsorted(sorted_image_ids, image_id, "right")]
        if mine.size:
            point2D_indices, point3D_ids = points.point2D_indices[mine], point3D_of_element[mine]
            order = np.lexsort((point3D_ids, point2D_indices))
            point2D_indices, point3D_ids = point2D_indices[order], point3D_ids[order]
            claimed_twice = (point2D_indices[1:] == point2D_indices[:-1]) & (point3D_ids[1:] != point3D_ids[:-1])
            if np.any(claimed_twice):
                index = int(point2D_indices[1:][claimed_twice][0])
                raise InputError(f"keypoint {index} of image {image_id} observed by two 3D points",
                                 field="structure.observations")
            points2D["point3D_id"][point2D_indices] = point3D_ids
        offset += num_points2D * _POINT2D.itemsize
    return bytes(payload)


def _model_reconstruction(pycolmap, scene: SfMScene, workdir: Path):
    """The sparse model of ``scene`` as a pycolmap.Reconstruction: cameras and images built
    with pycolmap, the 3D points written as points3D.bin with numpy (no Python object per
    point or track element) and read back by pycolmap (its reader links everything)."""
    posed = [view_id for view_id in sorted(scene.views) if view_id in scene.poses]
    points, extra_points2D = _model_points(scene, posed)
    _reconstruction(pycolmap, scene, posed, extra_points2D).write_binary(str(workdir))
    _check_written(workdir)
    images_path = workdir / "images.bin"
    images_path.write_bytes(_link_points2D(images_path.read_bytes(), points))
    (workdir / "points3D.bin").write_bytes(_points3D_bin(points))
    reconstruction = pycolmap.Reconstruction(str(workdir))
    reconstruction.update_point_3d_errors()  # points3D ERROR = mean reprojection error (px)
    return reconstruction


def model_reconstruction(scene: SfMScene):
    """The sparse model of ``scene`` (its posed views and structure) as an in-memory
    pycolmap.Reconstruction, e.g. for pycolmap's bundle adjuster."""
    pycolmap = import_pycolmap()
    with tempfile.TemporaryDirectory(prefix="rotonly-model-") as workdir:
        return _model_reconstruction(pycolmap, scene, Path(workdir))


def _observation_pixel(scene: SfMScene, point_index: int, row: int) -> np.ndarray:
    structure = scene.structure
    assert structure is not None
    if structure.observation_pixels is not None:
        return np.asarray(structure.observation_pixels[point_index][row], dtype=np.float64)
    view_id, feature = structure.observations[point_index][row]
    intrinsic = to_colmap_intrinsics(scene.intrinsics[scene.views[view_id].intrinsics_id])
    pose = scene.poses[view_id]
    point_in_camera = pose.R_cam_from_world @ (structure.points[point_index] - pose.center)
    camera = pycolmap_camera(intrinsic)
    return np.asarray(camera.img_from_cam(point_in_camera.reshape(1, 3)), dtype=np.float64)[0]


def _check_written(folder: Path, expected_sizes: dict[str, int] | None = None) -> None:
    """pycolmap writes with C++ streams that ignore errors: on a full disk it leaves short
    files and says nothing. The model it wrote is read back (model_check); a short one is the
    OSError the write should have raised (ENOSPC when the file system is full, else EIO).
    ``expected_sizes``: the file sizes of the same model written before and checked; files of
    exactly those sizes are complete, and the read-back is skipped (it is the slow part)."""
    if expected_sizes and all(os.path.getsize(folder / name) == size for name, size in expected_sizes.items()):
        return
    try:
        check_model(folder)
    except InputError as exc:
        raise atomic.unreported_write_error(folder, f"pycolmap wrote an unreadable model ({exc})") from None


def write_model(out_dir: PathLike, scene: SfMScene, binary: bool = True) -> None:
    """Write the posed views of ``scene`` as a COLMAP sparse model (cameras, images, points3D,
    rigs, frames; binary or text). Views without a pose are omitted. Staged in a temporary
    folder beside ``out_dir``: a new ``out_dir`` appears by one rename, an existing one
    receives the files one rename each."""
    pycolmap = import_pycolmap()
    out_dir = Path(out_dir)
    with atomic.filling_dir(out_dir) as staging:
        with tempfile.TemporaryDirectory(prefix=f".{out_dir.name}.points.", dir=out_dir.parent) as workdir:
            reconstruction = _model_reconstruction(pycolmap, scene, Path(workdir))
            # the binary files pycolmap read it from (images.bin and points3D.bin written by
            # rotonly, with Python's error checks): writing it again gives files of these sizes
            sizes = {entry.name: entry.stat().st_size for entry in os.scandir(workdir)}
        if binary:
            reconstruction.write_binary(str(staging))
        else:
            reconstruction.write_text(str(staging))
        _check_written(staging, sizes if binary else None)


def to_reconstruction(scene: SfMScene):
    """The posed views and the points of ``scene`` as a pycolmap.Reconstruction: the model
    :func:`write_model` writes."""
    pycolmap = import_pycolmap()
    with tempfile.TemporaryDirectory(prefix="rotonly-model-") as workdir:
        return _model_reconstruction(pycolmap, scene, Path(workdir))


def read_model(path: PathLike, poses_only: bool = False) -> SfMScene:
    """COLMAP sparse model folder -> SfMScene with cameras, (registered) views, poses,
    keypoints = the images' points2D, normalized, and structure with tracks and colours
    (``poses_only``: no keypoints and no structure)."""
    pycolmap = import_pycolmap()
    path = Path(path)
    if not path.exists():
        raise InputError("no such folder", path=str(path))
    if not is_colmap_model(path):
        raise InputError("not a COLMAP model (needs cameras, images, points3D .bin or .txt)",
                         path=str(path))
    check_model(path)  # every file in a layout pycolmap reads: its own messages never reach the user
    try:
        reconstruction = pycolmap.Reconstruction(str(path))
    except Exception:  # noqa: BLE001 - a disagreement check_model does not know; pycolmap's text is internal
        raise InputError("pycolmap cannot read this model (its files disagree with each other)",
                         path=str(path)) from None
    return scene_from_reconstruction(reconstruction, poses_only)


def scene_from_reconstruction(reconstruction, poses_only: bool = False) -> SfMScene:
    """A pycolmap.Reconstruction (in memory) as an SfMScene, as :func:`read_model` reads one."""
    scene = SfMScene(source="colmap-model")
    for camera_id, camera in reconstruction.cameras.items():
        scene.intrinsics[int(camera_id)] = Intrinsics(
            int(camera_id), camera.model.name, int(camera.width), int(camera.height),
            np.array(camera.params, dtype=np.float64))
    for image_id in sorted(reconstruction.images):
        image = reconstruction.images[image_id]
        camera = reconstruction.cameras[image.camera_id]
        scene.views[int(image_id)] = View(int(image_id), image.name, int(image.camera_id),
                                          width=int(camera.width), height=int(camera.height))
        if not poses_only:
            points = image.points2D
            keypoints = (np.array([p.xy for p in points], dtype=np.float64).reshape(-1, 2)
                         if len(points) else np.zeros((0, 2)))
            scene.keypoints[int(image_id)] = keypoints
            scene.normalized[int(image_id)] = normalize_keypoints(camera, keypoints)
        if image.has_pose:
            cam_from_world = image.cam_from_world()
            R = np.array(cam_from_world.rotation.matrix(), dtype=np.float64)
            t = np.array(cam_from_world.translation, dtype=np.float64)
            scene.poses[int(image_id)] = Pose(R, -R.T @ t)
    point_ids = [] if poses_only else sorted(reconstruction.points3D)
    if point_ids:
        points3D = [reconstruction.points3D[point_id] for point_id in point_ids]
        scene.structure = Structure(
            point_ids=np.array(point_ids, dtype=np.int64),
            points=np.array([p.xyz for p in points3D], dtype=np.float64).reshape(-1, 3),
            colors=np.array([p.color for p in points3D], dtype=np.uint8).reshape(-1, 3),
            observations=[[(int(e.image_id), int(e.point2D_idx)) for e in p.track.elements]
                          for p in points3D])
    return scene
