"""The pairs of ``rotonly bench strecha``: those rotonly's own front end keeps, read off a
``rotonly run`` of the scene's database.

The run is the product as ``rotonly run database.db`` runs it (pipeline.run_in_memory, the
CLI's options, no ground truth). Its stages are watched (run_stages' ``observe``): after scene
identification the load stage's relative poses of the edges still active (re-estimated by
RANSAC, the minimum-inlier and rotation-singular filters applied) are the *initial* poses;
after rotation averaging the edges still active (its outlier-edge filter applied) are the
*kept pairs*, with the inlier matches that rotonly's GRRM optimises. With the intrinsics
calibrated, the last pass is the one read (it is the result's). Every method of the benchmark
starts from these pairs, these initial poses and these matches; the run's own final rotations
are its ``rotonly run`` row.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class KeptPairs:
    """The pairs a run keeps before GRRM and what it started them from."""

    view_ids: list[int]  #: every view of the input, sorted (view id = COLMAP image id)
    names: dict[int, str]  #: view id -> image name
    keys: list[tuple[int, int]]  #: the kept pairs (i < j), sorted
    R_init: np.ndarray  #: (E, 3, 3) the load stage's R_j_from_i of each kept pair
    t_init: np.ndarray  #: (E, 3) its unit t_ij
    matches: list[np.ndarray]  #: per pair (m, 2) inlier keypoint indices [view i, view j]
    x_i: list[np.ndarray]  #: per pair (m, 2) normalized coordinates of the matches in view i
    x_j: list[np.ndarray]
    num_keypoints: np.ndarray  #: (n,) keypoints per view (rows = view_ids)
    num_input_pairs: int  #: the pairs of the input (the load stage's edges)
    filtered: dict[str, int] = field(default_factory=dict)  #: pairs left out before GRRM, per reason
    #: (n, 3, 3) the rotations ``rotonly run`` writes (views with a rotation and a centre), rows =
    #: view_ids, NaN = not written
    run_rotations: np.ndarray | None = None
    run_seconds: float = float("nan")  #: that run's time

    def named_pairs(self) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """{(image name i, image name j): (R_init, t_init, matches)} (baselines.references'
        pycolmap_global_mapper ``pairs``)."""
        return {(self.names[i], self.names[j]): (self.R_init[k], self.t_init[k], self.matches[k])
                for k, (i, j) in enumerate(self.keys)}


class _Watch:
    """run_stages' ``observe``: copies what the bench needs as the stages pass (the last pass wins)."""

    def __init__(self) -> None:
        self.initial: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.kept: list[tuple[int, int, np.ndarray]] = []
        self.normalized: dict = {}
        self.num_edges = 0
        self.filtered: dict[str, int] = {}

    def __call__(self, stage: str, run) -> None:
        edges = [run.graph.edges[k] for k in run.graph.active_edges()]
        if stage == "identify":  # the load stage's poses, the identification's filter applied
            self.initial = {(e.i, e.j): (np.array(e.R_j_from_i, dtype=float), np.array(e.t_dir, dtype=float))
                            for e in edges}
        elif stage == "average":  # what GRRM gets: the averaging's outlier-edge filter applied
            self.kept = [(e.i, e.j, np.array(e.matches, dtype=np.int64)) for e in edges]
            self.normalized = run.scene.normalized
            self.num_edges = len(run.graph.edges)
            self.filtered = run.graph.counts()["filtered_by_reason"]


def kept_pairs(source, options=None, kind=None, label: str | None = None) -> KeptPairs:
    """``rotonly run`` on ``source`` (a database path, or a scene read from one: then ``kind``
    and ``label`` say so) in memory; its kept pairs and final rotations. ``options``: the run's
    (default: the CLI's, progress off)."""
    from rotonly_cli.options import RunOptions
    from rotonly_cli.pipeline import run_in_memory

    options = options or RunOptions(progress=False)
    watch = _Watch()
    package_logger = logging.getLogger("rotonly_cli")
    level = package_logger.level
    package_logger.setLevel(max(logging.WARNING, package_logger.getEffectiveLevel()))  # the run's warnings only
    start = time.perf_counter()
    try:
        run = run_in_memory(source if kind is not None else Path(source), options, kind=kind, label=label,
                            observe=watch)
    finally:
        package_logger.setLevel(level)
    seconds = time.perf_counter() - start
    view_ids = run.graph.view_ids()
    kept = sorted(watch.kept, key=lambda e: (e[0], e[1]))
    keys = [(i, j) for i, j, _ in kept]
    matches = [m for _, _, m in kept]
    R_init = np.array([watch.initial[k][0] for k in keys], dtype=float).reshape(-1, 3, 3)
    t_init = np.array([watch.initial[k][1] for k in keys], dtype=float).reshape(-1, 3)
    rotations = np.array(run.rotations, dtype=float)
    rotations[~np.all(np.isfinite(run.centers), axis=1)] = np.nan  # not written without a centre
    return KeptPairs(view_ids=view_ids, names={v: run.scene.views[v].name for v in view_ids}, keys=keys,
                     R_init=R_init, t_init=t_init, matches=matches,
                     x_i=[watch.normalized[i][m[:, 0]] for (i, _), m in zip(keys, matches)],
                     x_j=[watch.normalized[j][m[:, 1]] for (_, j), m in zip(keys, matches)],
                     num_keypoints=np.array([len(watch.normalized.get(v, ())) for v in view_ids], dtype=np.int64),
                     num_input_pairs=watch.num_edges, filtered=dict(watch.filtered), run_rotations=rotations,
                     run_seconds=seconds)
