"""Where a view's image file is, and whether rotonly may read it (for the point colours).

A view names its image relative to the image folder (OpenMVG ``root_path`` with
``local_path/filename``, a COLMAP image name, ``--image-path``). :func:`image_file` keeps
that promise: a name that is absolute or climbs out of the folder (``../``) is never
opened, nor is a name that is not an image file name or a path that is not a regular file
(a named pipe would block the reader). The check is on the name, so an image folder of
symbolic links keeps working.
"""

from __future__ import annotations

import os
import posixpath
import stat
from pathlib import Path

PathLike = str | os.PathLike

#: what OpenCV's imread decodes (by file name; the content decides in the end)
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".jpe", ".png", ".tif", ".tiff", ".bmp", ".dib", ".webp", ".jp2",
                            ".pbm", ".pgm", ".ppm", ".pxm", ".pnm", ".pfm", ".sr", ".ras", ".exr", ".hdr", ".pic"})


def unsafe_image_name(name: str) -> str | None:
    """Why ``name`` must not be read as an image below an image folder, or None: absolute,
    climbing out of the folder (``/`` or ``\\`` separated), empty, or not an image."""
    if not name or "\0" in name:
        return "not a file name"
    for separator_free in (name, name.replace("\\", "/")):
        if separator_free.startswith("/") or (len(separator_free) > 1 and separator_free[1] == ":"):
            return "an absolute file name, outside the image folder"
        normal = posixpath.normpath(separator_free)
        if normal == ".." or normal.startswith("../"):
            return "climbs out of the image folder"
    if posixpath.splitext(name)[1].lower() not in IMAGE_SUFFIXES:
        return "not an image file name"
    return None


def image_file(root: PathLike, name: str) -> tuple[Path | None, str | None]:
    """(the image file of view image ``name`` under ``root``, None) when it may be read,
    else (None, why not): :func:`unsafe_image_name`, "missing", or "not a regular file"."""
    reason = unsafe_image_name(name)
    if reason is not None:
        return None, reason
    path = Path(root) / name
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None, "missing"
    if not stat.S_ISREG(mode):
        return None, "not a regular file"
    return path, None
