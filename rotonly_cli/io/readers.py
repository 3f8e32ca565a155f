"""The inputs of `rotonly run`, one entry per kind (io/detect.InputKind) in :data:`READERS`: what
can be checked before anything is written, how the scene with its matches is read, what was
read (reports/load.json), where the images are, and whose conventions the scene carries. The
load stage, the chain, the export and pipeline.check_input ask this table (`rotonly convert`
branches on its input and output kinds together: a conversion, not a run's reading)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.scene.types import SfMScene


@dataclass(frozen=True)
class Reader:
    """How `rotonly run` reads one kind of input."""

    #: (path) -> None: what can be checked before anything is written (InputError otherwise)
    check: Callable[[Path], None]
    #: (path, matches_dir, matches_file, scratch_dir) -> the scene with its matches
    read: Callable[..., SfMScene]
    #: (path, scene, matches_dir, matches_file) -> what ``read`` read, for reports/load.json
    files: Callable[..., dict]
    #: (path, scene) -> the image folder (point colours) when --image-path is not given; None: unknown
    image_root: Callable[[Path, SfMScene], Path | None]
    #: OUT/sfm_data.json keeps the input's root_path (else: the image folder found)
    keeps_root_path: bool
    #: the scene carries COLMAP's ids (OUT/sfm_data.json renumbers the views in file-name order)
    colmap_ids: bool
    #: its cameras follow OpenMVG's conventions (a camera guessed for it, as OpenMVG's image listing makes one)
    openmvg_cameras: bool


def _sfm_data(path: Path) -> Path:
    """An OpenMVG input's sfm_data.json (the input itself, or the one in the folder)."""
    return path / "sfm_data.json" if path.is_dir() else path


def _check_database(path: Path) -> None:
    from rotonly_cli.io.colmap.database_check import check_database

    check_database(path)


def _read_database(path: Path, matches_dir, matches_file, scratch_dir) -> SfMScene:
    from rotonly_cli.io import colmap

    return colmap.read_database(path, scratch_dir=scratch_dir)


def _database_images(path: Path, scene: SfMScene) -> Path | None:
    """``images/`` beside the database, as COLMAP lays a project out."""
    candidate = path.parent / "images"
    return candidate if path.is_file() and candidate.is_dir() else None


def _read_project(path: Path, matches_dir, matches_file, scratch_dir) -> SfMScene:
    from rotonly_cli.io import openmvg

    sfm_data = _sfm_data(path)
    scene = openmvg.read_project(sfm_data, matches_dir, matches_file)
    if not scene.pairs:
        raise InputError("no matches file (matches.e/f/putative .bin|.txt) beside the features",
                         path=str(matches_dir or sfm_data.parent), field="--matches-dir")
    return scene


def _project_files(path: Path, scene: SfMScene, matches_dir, matches_file) -> dict:
    """The sfm_data.json, each view's ``.feat`` and the matches file; the matches file chosen."""
    from rotonly_cli.io import openmvg

    files, chosen = openmvg.project_files(scene, _sfm_data(path), matches_dir, matches_file)
    return {"input_files": files, "matches_file": chosen}


def _project_images(path: Path, scene: SfMScene) -> Path | None:
    """root_path the way OpenMVG's tools read it (from the current directory), else from the
    sfm_data.json folder."""
    from rotonly_cli.io.openmvg import image_root

    return image_root(scene.root_path, _sfm_data(path))


def _read_model(path: Path, matches_dir, matches_file, scratch_dir) -> SfMScene:
    raise InputError("a COLMAP model holds no matches; give the COLMAP database or an OpenMVG sfm_data.json",
                     path=str(path))


def _the_file(path: Path, scene: SfMScene, matches_dir=None, matches_file=None) -> dict:
    return {"input_files": [str(path)]}


def _nothing(*args) -> None:
    return None


READERS = {
    InputKind.COLMAP_DB: Reader(check=_check_database, read=_read_database, files=_the_file,
                                image_root=_database_images, keeps_root_path=False, colmap_ids=True,
                                openmvg_cameras=False),
    InputKind.OPENMVG: Reader(check=_nothing, read=_read_project, files=_project_files, image_root=_project_images,
                              keeps_root_path=True, colmap_ids=False, openmvg_cameras=True),
    InputKind.COLMAP_MODEL: Reader(check=_nothing, read=_read_model, files=_the_file, image_root=_nothing,
                                   keeps_root_path=False, colmap_ids=True, openmvg_cameras=False),
}
