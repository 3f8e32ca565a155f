"""Public multi-view API (architecture.md "Python API contract", stable).

    from rotonly_cli import multiview
    multiview.optimize_rotations(rotations, observations, edges) -> GlobalRotations(...)

``rotations``: {view_id: R_cam_from_world (3, 3)} initial global rotations (e.g. from robust
rotation averaging); ``observations``: {view_id: (k, 2) normalized coordinates of that view's
keypoints}; ``edges``: {(i, j): (m, 2) int array of matched keypoint indices [in view i, in
view j]}. Returns the GRRM-optimised rotations (paper Alg. 3-4).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.grrm import GRRMOptions, GRRMResult, optimize_global_rotations

__all__ = ["GlobalRotations", "GRRMOptions", "GRRMProblem", "build_problem", "optimize_rotations"]


@dataclass(frozen=True)
class GlobalRotations:
    rotations: dict  #: {view_id: refined R_cam_from_world}
    initial_cost: float
    cost: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)


@dataclass
class GRRMProblem:
    """GRRM inputs in array form: view ids in index order, edges as index pairs, matches."""

    view_ids: list
    edge_views: np.ndarray  # (E, 2) indices into view_ids
    batch: pg.EdgeBatch
    obs_ids: np.ndarray  # (M, 2) unique observation ids (view offset + keypoint index)
    pair_keys: list  # (i, j) view-id pairs, in edge order


def build_problem(observations: Mapping, edges: Mapping, view_ids: list | None = None) -> GRRMProblem:
    """Arrays for :func:`rotonly_cli.geometry.grrm.optimize_global_rotations` from per-view
    keypoints and per-pair match indices. Edges with fewer than 6 matches are skipped."""
    if view_ids is None:
        view_ids = sorted({v for key in edges for v in key})
    index = {v: k for k, v in enumerate(view_ids)}
    sizes = np.array([len(observations[v]) for v in view_ids], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(sizes)])
    keys, xs_i, xs_j, ids = [], [], [], []
    for (i, j), matches in sorted(edges.items()):
        if i not in index or j not in index:
            raise ValueError(f"edges: pair {(i, j)} names a view without observations")
        matches = np.asarray(matches, dtype=np.int64).reshape(-1, 2)
        if len(matches) < pg.MIN_MATCHES:
            continue
        obs_i = np.asarray(observations[i], dtype=float)
        obs_j = np.asarray(observations[j], dtype=float)
        if matches.min(initial=0) < 0 or matches[:, 0].max(initial=-1) >= len(obs_i) or \
                matches[:, 1].max(initial=-1) >= len(obs_j):
            raise ValueError(f"edges: pair {(i, j)} has a keypoint index out of range")
        keys.append((i, j))
        xs_i.append(obs_i[matches[:, 0]])
        xs_j.append(obs_j[matches[:, 1]])
        ids.append(np.stack([offset[index[i]] + matches[:, 0], offset[index[j]] + matches[:, 1]], axis=1))
    batch = pg.pack_edges(xs_i, xs_j)
    edge_views = np.array([[index[i], index[j]] for i, j in keys], dtype=np.int64).reshape(-1, 2)
    obs_ids = np.concatenate(ids) if ids else np.zeros((0, 2), dtype=np.int64)
    return GRRMProblem(view_ids=list(view_ids), edge_views=edge_views, batch=batch, obs_ids=obs_ids, pair_keys=keys)


def optimize_rotations(rotations: Mapping, observations: Mapping, edges: Mapping, fixed_view=None,
                       options: GRRMOptions = GRRMOptions()) -> GlobalRotations:
    """GRRM (Alg. 4) from initial rotations; ``fixed_view`` (a view id) defaults to the first."""
    view_ids = sorted(rotations)
    problem = build_problem(observations, edges, view_ids)
    R0 = np.stack([np.asarray(rotations[v], dtype=float) for v in view_ids])
    fixed = 0 if fixed_view is None else view_ids.index(fixed_view)
    res: GRRMResult = optimize_global_rotations(R0, problem.edge_views, problem.batch, problem.obs_ids,
                                                fixed_view=fixed, options=options)
    return GlobalRotations(rotations={v: res.R_cam_from_world[k] for k, v in enumerate(view_ids)},
                           initial_cost=res.initial_cost, cost=res.cost, iterations=res.iterations,
                           converged=res.converged, history=res.history)
