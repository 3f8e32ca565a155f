"""The whole chain from Python, in memory: ``rotonly_cli.run(...)``.

    import rotonly_cli
    result = rotonly_cli.run("database.db")              # or an sfm_data.json, a pycolmap.Reconstruction,
    result.rotations[view_id], result.centers[view_id]   # a pycolmap.Database or an SfMScene
    result.points, result.colors, result.to_pycolmap()

The stages and options are `rotonly run`'s (the keyword names are the CLI's options), and
so are the numbers: the rotations equal those ``rotonly run`` writes to ``sfm_data.json``
bit for bit. With ``out`` the workspace is written too, as ``rotonly run INPUT -o OUT`` does.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.options import RunOptions, cluster_address
from rotonly_cli.scene.types import PairMatches, SfMScene, Structure
from rotonly_cli.scene.view_graph import ViewGraph

__all__ = ["RunResult", "run", "pairs_from_tracks"]


@dataclass
class RunResult:
    """What a run estimated. Views are the input's ids (COLMAP image ids, OpenMVG view ids)."""

    rotations: dict[int, np.ndarray]  #: view id -> R_cam_from_world (3, 3), registered views only
    centers: dict[int, np.ndarray]  #: view id -> camera centre (3,) in world coordinates
    points: np.ndarray  #: (N, 3) points in world coordinates
    colors: np.ndarray  #: (N, 3) uint8 RGB (grey without images)
    observations: list[list[tuple[int, int]]]  #: per point its (view id, keypoint index) pairs
    view_names: dict[int, str]  #: every input view's image name
    unregistered_views: list[int]  #: views without a pose
    reports: dict  #: the stage reports (reports/<stage>.json of `rotonly run`)
    scene: SfMScene  #: the output scene (cameras, views, poses, keypoints, structure)
    graph: ViewGraph  #: the view graph with every edge's status and diagnostics
    summary: dict = field(default_factory=dict)  #: what `rotonly run` prints (and reports/run.json)
    evaluation: dict | None = None  #: with ``gt``: the comparison (rotonly eval's report.json)

    def to_pycolmap(self):
        """The poses and points as a pycolmap.Reconstruction (OUT/sparse/ of `rotonly run`)."""
        from rotonly_cli.io.colmap import to_reconstruction

        return to_reconstruction(self.scene)


def pairs_from_tracks(structure: Structure) -> dict[tuple[int, int], PairMatches]:
    """Matches between every two views of every track (observations of one view twice in a
    track are skipped): what a COLMAP model holds of its matches. Unverified, without a
    relative pose, so the load stage estimates one."""
    track_lengths, view_feature = structure.flat_observations()
    track_lengths = np.asarray(track_lengths, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(track_lengths)[:-1]]).astype(np.int64)
    rows_a, rows_b = [], []
    for length in np.unique(track_lengths).tolist():
        first = starts[track_lengths == length]
        a, b = np.triu_indices(length, k=1)
        rows_a.append((first[:, None] + a[None, :]).ravel())
        rows_b.append((first[:, None] + b[None, :]).ravel())
    if not rows_a:
        return {}
    obs_a, obs_b = view_feature[np.concatenate(rows_a)], view_feature[np.concatenate(rows_b)]
    swap = obs_a[:, 0] > obs_b[:, 0]
    obs_a[swap], obs_b[swap] = obs_b[swap].copy(), obs_a[swap].copy()
    keep = obs_a[:, 0] != obs_b[:, 0]
    obs_a, obs_b = obs_a[keep], obs_b[keep]
    order = np.lexsort((obs_b[:, 1], obs_a[:, 1], obs_b[:, 0], obs_a[:, 0]))
    obs_a, obs_b = obs_a[order], obs_b[order]
    pair_keys = np.stack([obs_a[:, 0], obs_b[:, 0]], axis=1)
    bounds = np.flatnonzero(np.any(np.diff(pair_keys, axis=0) != 0, axis=1)) + 1
    pairs = {}
    for start, end in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(pair_keys)]])):
        i, j = (int(v) for v in pair_keys[start])
        matches = np.unique(np.stack([obs_a[start:end, 1], obs_b[start:end, 1]], axis=1), axis=0)
        pairs[(i, j)] = PairMatches(i, j, matches.astype(np.int64), verified=True)
    return pairs


def _scene_input(source) -> tuple[SfMScene, InputKind, str] | None:
    """(scene, kind, label) for an in-memory input; None for a path."""
    if isinstance(source, (str, os.PathLike)):
        return None
    if isinstance(source, SfMScene):
        kind = InputKind.OPENMVG if source.source == "openmvg" else InputKind.COLMAP_DB
        return source, kind, "<SfMScene>"
    import pycolmap

    from rotonly_cli.io import colmap

    if isinstance(source, pycolmap.Reconstruction):
        scene = colmap.scene_from_reconstruction(source)
        if scene.structure is not None:
            scene.pairs = pairs_from_tracks(scene.structure)
        scene.poses, scene.structure = {}, None  # estimated anew
        return scene, InputKind.COLMAP_MODEL, "<pycolmap.Reconstruction>"
    if isinstance(source, pycolmap.Database):
        return colmap.read_database(source), InputKind.COLMAP_DB, "<pycolmap.Database>"
    raise InputError(f"expected a path, a pycolmap.Reconstruction, a pycolmap.Database or an SfMScene, got "
                     f"{type(source).__name__}", field="input")


def _options(options: RunOptions | None, settings: dict) -> RunOptions:
    """``options`` with the CLI-named ``settings`` applied (options.settings); without
    ``options``, the CLI's defaults (RunOptions(), and ``jobs`` = the usable CPUs)."""
    from rotonly_cli.options.settings import with_settings

    if options is None:
        from rotonly_cli.runtime.parallel import usable_cpus

        options = RunOptions(jobs=usable_cpus())
    return with_settings(options, settings)


def run(input, out: str | os.PathLike | None = None, *, gt=None, matches_dir=None, matches=None, image_path=None,
        min_inliers: int | None = None, reestimate: str | None = None, ransac_max_error: float | None = None,
        seed: int | None = None, consensus: str | None = None, intrinsics: str | None = None,
        max_residual_deg: float | None = None, grrm: bool | None = None, jobs: int | None = None,
        cluster: str | None = None, progress: bool | None = None, max_memory: float | None = None,
        options: RunOptions | None = None) -> RunResult:
    """`rotonly run` in memory: camera poses and points from feature matches.

    ``input``: a COLMAP database or an OpenMVG sfm_data.json (path), a ``pycolmap.Database``,
    a ``pycolmap.Reconstruction`` (its tracks give the matches; its poses are not used) or an
    :class:`~rotonly_cli.scene.types.SfMScene`. The keywords are the CLI options of `rotonly
    run` (``matches`` is -M, ``grrm=False`` is --no-grrm, ``max_memory`` is --max-memory in GB,
    ``cluster`` is --cluster: ``"tcp://HOST:PORT"`` or ``"local:N"``, needing the extra 'cluster';
    defaults as there: ``jobs`` = the usable CPUs) and override ``options`` (all of them, as
    RunOptions). With ``out`` the workspace is written as `rotonly run INPUT -o OUT` writes it. Errors: InputError
    (ValueError) for bad input, AlgorithmError when no result is possible.
    """
    from rotonly_cli import pipeline

    options = _options(options, {"gt": gt, "matches_dir": matches_dir, "matches": matches, "image_path": image_path,
                                 "min_inliers": min_inliers, "reestimate": reestimate,
                                 "ransac_max_error": ransac_max_error, "seed": seed, "consensus": consensus,
                                 "intrinsics": intrinsics,
                                 "max_residual_deg": max_residual_deg, "grrm": grrm, "jobs": jobs,
                                 "cluster": cluster, "progress": progress, "max_memory": max_memory})
    options.load.validate()
    if options.max_memory_gb is not None and not 0 < options.max_memory_gb < float("inf"):
        raise InputError(f"{options.max_memory_gb} is not a positive number of GB", field="max_memory")
    options.intrinsics.validate()
    options.reject.validate()
    if options.cluster is not None:
        cluster_address(options.cluster)
    in_memory = _scene_input(input)
    source, kind, label = (Path(input), None, None) if in_memory is None else in_memory
    evaluation = None
    if out is not None:
        summary, result = pipeline.run_into(source, out, options, kind=kind, label=label)
        scene = pipeline.output_scene(result)
    else:
        gt_scene = pipeline.ground_truth_for(options, pipeline.STAGES)
        result = pipeline.run_in_memory(source, options, kind=kind, label=label)
        scene = pipeline.output_scene(result)
        summary = {"input": result.input_path, "num_views": len(result.scene.views), "num_registered": len(scene.poses),
                   "num_points": 0 if scene.structure is None else len(scene.structure.points),
                   "num_active_edges": len(result.graph.active_edges())}
        pipeline.summarize_outcome(result, scene, summary)
        if gt_scene is not None:
            from rotonly_cli.evaluation.quality import evaluate

            evaluation = evaluate(gt_scene, scene).to_dict()
            summary["rotation_error_deg"] = evaluation.get("rotation_error_deg")
            pipeline.gt_warning(result, evaluation, summary)
    if out is not None and options.gt:
        import json

        evaluation = json.loads((Path(out) / "eval" / "report.json").read_text())
    structure = scene.structure
    view_ids = result.graph.view_ids()
    return RunResult(
        rotations={v: scene.poses[v].R_cam_from_world for v in view_ids if v in scene.poses},
        centers={v: scene.poses[v].center for v in view_ids if v in scene.poses},
        points=np.zeros((0, 3)) if structure is None else np.asarray(structure.points),
        colors=np.zeros((0, 3), dtype=np.uint8) if structure is None or structure.colors is None
        else np.asarray(structure.colors),
        observations=[] if structure is None else structure.observations,
        view_names={v: result.scene.views[v].name for v in view_ids},
        unregistered_views=[v for v in view_ids if v not in scene.poses], reports=dict(result.reports),
        scene=scene, graph=result.graph, summary=summary, evaluation=evaluation)

