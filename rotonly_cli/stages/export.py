"""Stage `export`: the estimated poses and points written as ``OUT/sfm_data.json`` (OpenMVG)
and ``OUT/sparse/`` (COLMAP binary model)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.io.readers import READERS
from rotonly_cli.scene.types import Pose, SfMScene, Structure


def posed_scene(scene: SfMScene, view_ids: list[int], rotations: np.ndarray | None, centers: np.ndarray | None,
                structure: Structure | None, image_root: str | Path | None) -> SfMScene:
    """``scene`` with the estimated poses (rows of ``view_ids`` with a finite rotation and
    centre), the points, no pairs, and ``root_path`` = ``image_root`` (when given)."""
    poses = {}
    if rotations is not None and centers is not None:
        for row, view_id in enumerate(view_ids):
            if np.all(np.isfinite(rotations[row])) and np.all(np.isfinite(centers[row])):
                poses[view_id] = Pose(rotations[row].copy(), centers[row].copy())
    return replace(scene, poses=poses, structure=structure, pairs={},
                   root_path=str(image_root) if image_root is not None else scene.root_path)


def write_outputs(out_dir: Path, scene: SfMScene, input_kind: InputKind, jobs: int = 1,
                  sfm_data_name: str = "sfm_data.json", sparse_name: str = "sparse"):
    """OUT/sfm_data.json and OUT/sparse/ of a :func:`posed_scene` (``sfm_data_name``,
    ``sparse_name``: other names inside OUT, for another component's model). With ``jobs`` > 1 the
    sfm_data.json is written by a forked child (runtime.parallel.ForkedCall; the same bytes)
    while this process writes the COLMAP model and goes on: call ``result()`` of the returned
    handle before OUT is complete (it raises the child's error, if any)."""
    from rotonly_cli.io import colmap, openmvg
    from rotonly_cli.runtime.parallel import ForkedCall
    from rotonly_cli.scene.ids import renumber_views_by_name

    if not scene.poses:
        raise AlgorithmError("no view received a pose (rotation and centre)")
    # COLMAP input: OpenMVG ids in file-name order (what OpenMVG's own tools, evalQuality
    # included, expect); the COLMAP model keeps the database's ids
    openmvg_scene = (renumber_views_by_name(colmap.colmap_to_openmvg(scene))
                     if READERS[input_kind].colmap_ids else scene)
    # formatting its ~10 numbers per observation is the export's largest cost (three quarters)
    sfm_data = ForkedCall(lambda: openmvg.write_sfm_data(out_dir / sfm_data_name, openmvg_scene), jobs > 1)
    try:
        colmap.write_model(out_dir / sparse_name, scene, binary=True)
    except BaseException:
        sfm_data.result()
        raise
    return sfm_data
