"""Every format sniff: what a path holds, recognised by content (SQLite magic, COLMAP model
files, ``sfm_data.json``, Strecha ``.camera`` files), and the one reader of ground truths and
estimates built on it (``rotonly eval``, ``rotonly run --gt``, the benchmarks)."""

from __future__ import annotations

import os
from pathlib import Path

from rotonly_cli.compat import StrEnum
from rotonly_cli.errors import InputError
from rotonly_cli.io.inputs import check_regular_file, open_input
from rotonly_cli.scene.types import SfMScene

PathLike = str | os.PathLike
SQLITE_MAGIC = b"SQLite format 3\x00"
MODEL_FILE_STEMS = ("cameras", "images", "points3D")
GT_SUBDIR = "gt_dense_cameras"


class InputKind(StrEnum):
    COLMAP_DB = "colmap-db"  #: a COLMAP database (SQLite)
    OPENMVG = "openmvg"  #: an OpenMVG sfm_data.json (or a folder holding one)
    COLMAP_MODEL = "colmap-model"  #: a COLMAP sparse model folder


def is_sqlite(path: PathLike) -> bool:
    """True if the file starts with SQLite's magic; InputError if it cannot be read or is
    not a regular file (a named pipe would block the read)."""
    with open_input(path) as stream:
        try:
            return stream.read(len(SQLITE_MAGIC)) == SQLITE_MAGIC
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror}", path=str(path)) from None


def is_colmap_model(path: PathLike) -> bool:
    """True if ``path`` holds cameras/images/points3D as .bin or .txt."""
    path = Path(path)
    return path.is_dir() and any(
        all((path / f"{stem}{ext}").is_file() for stem in MODEL_FILE_STEMS)
        for ext in (".bin", ".txt"))


def is_strecha_folder(path: PathLike) -> bool:
    """A Strecha scene folder (with ``gt_dense_cameras/``) or that folder itself."""
    path = Path(path)
    return (path / GT_SUBDIR).is_dir() or any(path.glob("*.camera"))


#: OpenMVG's other sfm_data serializations (cereal binary, XML), which rotonly does not read
OPENMVG_OTHER_SUFFIXES = (".bin", ".xml")


def unread_format_hint(path: Path) -> str:
    """What a file or folder rotonly cannot read seems to be, and what to do: an OpenMVG
    sfm_data.bin / .xml (OpenMVG writes them as readily as .json; its converter makes the
    .json), an OpenMVG matches file (the project is the input, the file its -M), or one file
    of a COLMAP model (its folder is the input); "" otherwise."""
    if path.is_dir():
        other = [path / f"sfm_data{suffix}" for suffix in OPENMVG_OTHER_SUFFIXES]
        path = next((candidate for candidate in other if candidate.is_file()), None)
        if path is None:
            return ""
    if path.stem in MODEL_FILE_STEMS:
        return f"; a COLMAP model is read from its folder: give {path.parent}"
    if path.name.startswith("matches.") and path.suffix.lower() in (".bin", ".txt"):
        project = path.parent / "sfm_data.json"
        return (f"; {path.name} looks like an OpenMVG matches file: give the project's sfm_data.json with this file "
                f"as -M" + (f" (rotonly run {project} -M {path} ...)" if project.is_file() else ""))
    if path.suffix.lower() in OPENMVG_OTHER_SUFFIXES:
        form = "binary" if path.suffix.lower() == ".bin" else "XML"
        return (f"; {path.name} looks like an OpenMVG sfm_data in {form} form, which rotonly does not read: "
                f"convert it with openMVG_main_ConvertSfM_DataFormat -i {path} "
                f"-o {path.with_suffix('.json')}")
    return ""


def database_hint(folder: Path) -> str:
    """For a folder given where a COLMAP database is read: the database it holds
    (``database.db`` first, else its only SQLite ``*.db``), as what to give instead; "" if none."""
    candidates = [folder / "database.db"] + sorted(p for p in folder.glob("*.db") if p.name != "database.db")
    found = []
    for candidate in candidates:
        try:
            if candidate.is_file() and is_sqlite(candidate):
                found.append(candidate)
        except InputError:  # unreadable: not the one to suggest
            pass
    if not found or (found[0].name != "database.db" and len(found) > 1):
        return ""
    return f"; it holds a COLMAP database: give {found[0]}"


def detect_input(path: Path) -> InputKind:
    """The kind of a `rotonly run` / `rotonly convert` input; InputError otherwise."""
    if not path.exists():
        raise InputError("no such file or folder", path=str(path))
    if path.is_dir():
        if is_colmap_model(path):
            return InputKind.COLMAP_MODEL
        if (path / "sfm_data.json").is_file():
            return InputKind.OPENMVG
        raise InputError("folder is neither a COLMAP model (cameras/images/points3D .bin|.txt) "
                         "nor an OpenMVG project (sfm_data.json)" + (database_hint(path) or unread_format_hint(path)),
                         path=str(path))
    if is_sqlite(path):
        return InputKind.COLMAP_DB
    if path.suffix.lower() == ".json":
        return InputKind.OPENMVG
    raise InputError("not an SQLite file (COLMAP database) nor an OpenMVG sfm_data .json" + unread_format_hint(path),
                     path=str(path))


def _reader(module: str, name: str):
    """Readers are imported lazily: the CLI loads fast and only needs the format it reads."""
    import importlib

    return getattr(importlib.import_module(f"rotonly_cli.io.{module}"), name)


def read_scene(path: PathLike, field: str | None = None, ground_truth: bool = True,
               poses_only: bool = False) -> SfMScene:
    """A ground truth or an estimate: an OpenMVG sfm_data .json file, a Strecha folder (its
    ``gt_dense_cameras/`` or the folder holding it; ground truth only), a COLMAP model, or a
    folder holding ``sfm_data.json`` or a COLMAP model in ``sparse/`` (a `rotonly run` OUT).
    ``field`` names the option in error messages. ``poses_only``: views, cameras and poses,
    no points or keypoints (all an evaluation reads; a simulated collection's ground truth
    holds 1 GB of points at 1000 views)."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path=str(path), field=field)
    if not path.is_dir():
        check_regular_file(path, field)
        if path.suffix.lower() != ".json":
            raise InputError("expected an OpenMVG sfm_data .json file or a folder" + unread_format_hint(path),
                             path=str(path), field=field)
        return _reader("openmvg", "read_sfm_data")(str(path), poses_only)
    if ground_truth and is_strecha_folder(path):
        return _reader("strecha", "read_strecha_dir")(str(path))
    if is_colmap_model(path):
        return _reader("colmap", "read_model")(str(path), poses_only)
    if (path / "sfm_data.json").is_file():
        return _reader("openmvg", "read_sfm_data")(str(path / "sfm_data.json"), poses_only)
    if is_colmap_model(path / "sparse"):
        return _reader("colmap", "read_model")(str(path / "sparse"), poses_only)
    expected = f"{GT_SUBDIR}/, *.camera, " if ground_truth else ""
    raise InputError(f"folder holds none of {expected}sfm_data.json, a COLMAP model (cameras/images .bin|.txt)"
                     + unread_format_hint(path), path=str(path), field=field)


def read_ground_truth(path: PathLike) -> SfMScene:
    """:func:`read_scene` of a ground truth (its poses)."""
    return read_scene(path, ground_truth=True, poses_only=True)
