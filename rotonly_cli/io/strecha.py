"""Strecha ground truth (``gt_dense_cameras/*.camera``) and ground-truth dispatch.

File layout (formats.md §3.2): K (3 rows), 3 distortion values (ignored), R (3 rows) that is
**camera -> world**, the camera centre C, then ``width height``. Poses are stored as
``R_cam_from_world = R_file^T`` with centre C, exactly as OpenMVG's evalQuality does; the
matrices are kept as written (Strecha's are not exactly orthonormal, and evalQuality uses
them unchanged). K is in the "top-left pixel centre = (0, 0)" convention (data README), so
the principal point gets +0.5 here to become COLMAP's.

View ids follow evalQuality's directory mode (§3.3): the index of the file in the sorted
list of ``.camera`` files; view id = intrinsics id = pose id.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import GT_SUBDIR
from rotonly_cli.io.inputs import check_camera, read_bytes
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, View

PathLike = str | os.PathLike
PIXEL_OFFSET = 0.5  # COLMAP pixel = Strecha/OpenMVG pixel + 0.5


def read_camera_file(path: PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int] | None]:
    """(K, R_cam_to_world as written, C, (width, height) or None) of one ``.camera`` file."""
    path = Path(path)
    try:
        values = np.array(read_bytes(path).decode("ascii").split(), dtype=np.float64)
    except UnicodeDecodeError:
        raise InputError("not ASCII text (a Strecha camera file)", path=str(path)) from None
    except ValueError:
        raise InputError("non-numeric value in a Strecha camera file", path=str(path)) from None
    # evalQuality accepts 26 values (24 + width/height... minus its extra EOF push); we need
    # K (9), distortion (3), R (9), C (3); width/height are optional.
    if values.size < 24:
        raise InputError(f"{values.size} numbers, a Strecha camera needs at least 24 "
                         "(K, 3 distortion, R, C)", path=str(path))
    for start, stop, field in ((0, 9, "K"), (9, 12, "distortion"), (12, 21, "R"), (21, 24, "C")):
        if not np.all(np.isfinite(values[start:stop])):
            raise InputError(f"non-finite value ({', '.join(map(str, values[start:stop]))})", path=str(path),
                             field=field)
    K = values[0:9].reshape(3, 3)
    R_cam_to_world = values[12:21].reshape(3, 3)
    center = values[21:24].copy()
    size = None
    if values.size >= 26:
        width, height = values[24:26]
        if not all(np.isfinite(v) and v >= 0 and v == int(v) for v in (width, height)):
            raise InputError(f"{width} {height}: expected two whole numbers >= 0", path=str(path),
                             field="width height")
        size = (int(width), int(height))
    return K, R_cam_to_world, center, size


def _camera_dir(path: Path) -> Path:
    if (path / GT_SUBDIR).is_dir():
        return path / GT_SUBDIR
    return path


def read_strecha_dir(path: PathLike) -> SfMScene:
    """Strecha scene folder (holding ``gt_dense_cameras/``) or that folder itself ->
    SfMScene with one PINHOLE intrinsic and one pose per ``<image name>.camera``."""
    path = Path(path)
    if not path.is_dir():
        raise InputError("no such folder", path=str(path))
    camera_dir = _camera_dir(path)
    camera_files = sorted(p for p in camera_dir.iterdir()
                          if p.is_file() and p.name.endswith(".camera"))
    if not camera_files:
        raise InputError("no .camera files (expected a Strecha gt_dense_cameras folder)",
                         path=str(camera_dir))
    scene = SfMScene(source="strecha", root_path=str(path / "images"))
    for view_id, camera_file in enumerate(camera_files):
        K, R_cam_to_world, center, size = read_camera_file(camera_file)
        name = camera_file.name[: -len(".camera")]  # "0000.jpg.camera" -> "0000.jpg"
        width, height = size if size is not None else (0, 0)
        if width <= 0 or height <= 0:  # evalQuality reads it from the image; guess from pp
            width, height = int(round(2 * (K[0, 2] + PIXEL_OFFSET))), int(round(
                2 * (K[1, 2] + PIXEL_OFFSET)))
        params = np.array([K[0, 0], K[1, 1], K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET])
        check_camera(camera_file, "K", width, height, params[:2], params[2:], params)
        scene.intrinsics[view_id] = Intrinsics(view_id, "PINHOLE", width, height, params)
        scene.views[view_id] = View(view_id, name, view_id, pose_id=view_id, width=width,
                                    height=height)
        scene.poses[view_id] = Pose(R_cam_from_world=R_cam_to_world.T.copy(), center=center)
    return scene
