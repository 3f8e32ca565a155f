"""`rotonly convert`: COLMAP database/model <-> OpenMVG project/sfm_data.json.

Formats are recognised by content (io/detect: SQLite magic, COLMAP model files,
``sfm_data.json``) and the output by its name: ``*.db`` -> COLMAP database, ``*.json`` ->
OpenMVG sfm_data, anything else -> a folder (OpenMVG project for COLMAP input, COLMAP model
for OpenMVG input). Ids are shifted between the two conventions (scene/ids).
"""

from __future__ import annotations

import os
from pathlib import Path

from rotonly_cli.errors import InputError, write_error
from rotonly_cli.io import atomic
from rotonly_cli.io.detect import InputKind, detect_input

PathLike = str | os.PathLike


def _output_kind(path: Path) -> str:
    suffix = path.suffix.lower()
    return {".db": "colmap-db", ".json": "sfm_data"}.get(suffix, "folder")


def convert(input_path: PathLike, output_path: PathLike, matches_dir: PathLike | None = None,
            text: bool = False, matches_file: PathLike | None = None) -> str:
    """Convert ``input_path`` to ``output_path``; returns a one-line summary."""
    from rotonly_cli.io import colmap, openmvg

    input_path, output_path = Path(input_path), Path(output_path)
    input_kind = detect_input(input_path)
    output_kind = _output_kind(output_path)
    if output_path.exists() and output_path.resolve() == input_path.resolve():
        raise InputError("output would overwrite the input", path=str(output_path))
    if output_kind != "folder" and output_path.is_dir():
        raise InputError("is a folder, expected a file name", path=str(output_path))
    if output_kind == "folder" and output_path.exists() and not output_path.is_dir():
        raise InputError("exists and is not a folder", path=str(output_path))

    if input_kind == InputKind.OPENMVG:
        sfm_data = input_path / "sfm_data.json" if input_path.is_dir() else input_path
        if output_kind == "colmap-db":
            scene = openmvg.read_project(sfm_data, matches_dir, matches_file)
        else:
            scene = openmvg.read_sfm_data(sfm_data)
    elif input_kind == InputKind.COLMAP_DB:
        colmap.check_database(input_path)  # before the scratch folder (and OUTPUT's parents) are made
        with atomic.scratch_dir(output_path) as scratch:  # the database's private copy, beside OUTPUT
            scene = colmap.read_database(input_path, scratch_dir=scratch)
    else:
        scene = colmap.read_model(input_path)

    def write() -> None:
        if output_kind == "colmap-db":
            colmap.write_database(output_path, scene)
        elif output_kind == "sfm_data":
            openmvg.write_sfm_data(output_path, colmap.colmap_to_openmvg(scene)
                                   if input_kind != InputKind.OPENMVG else scene)
        elif input_kind == InputKind.OPENMVG:
            if not scene.poses:
                raise InputError("no poses (extrinsics) to write as a COLMAP model",
                                 path=str(input_path), field="extrinsics")
            colmap.write_model(output_path, scene, binary=not text)
        else:
            openmvg.write_project(output_path, colmap.colmap_to_openmvg(scene))

    try:
        output_path.parent.mkdir(parents=True, exist_ok=True)
        write()
    except OSError as exc:
        raise write_error(exc, output_path) from None
    num_verified = sum(1 for pair in scene.pairs.values() if pair.verified)
    return (f"{input_kind} {input_path} -> {output_kind} {output_path}: {len(scene.views)} views, "
            f"{len(scene.poses)} poses, {num_verified} verified / {len(scene.pairs)} pairs, "
            f"{0 if scene.structure is None else len(scene.structure.points)} points")
