"""Public multi-view API (architecture.md "Python API contract", stable).

    from rotonly_cli import multiview
    multiview.average_rotations(relative_rotations) -> AveragedRotations(rotations, ...)
    multiview.optimize_rotations(rotations, observations, edges) -> GlobalRotations(...)

``relative_rotations``: {(i, j): R_j_from_i (3, 3)} (= R_j R_i^T); robust rotation averaging
(L1 + IRLS, the average stage of `rotonly run`) gives the global rotations they agree on.
``rotations``: {view_id: R_cam_from_world (3, 3)} initial global rotations (e.g. from
``average_rotations``); ``observations``: {view_id: (k, 2) normalized coordinates of that
view's keypoints (pixels are refused: twoview.PIXEL_LIKE)}; ``edges``: {(i, j): (m, 2) int
array of matched keypoint indices [in view i, in view j]}. ``optimize_rotations`` returns the
GRRM-optimised rotations (paper Alg. 3-4).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.averaging import AveragingOptions
from rotonly_cli.geometry.averaging import average_rotations as _average_rotations
from rotonly_cli.geometry.grrm import GRRMOptions, GRRMResult, optimize_global_rotations
from rotonly_cli.twoview import refuse_pixels

__all__ = ["AveragedRotations", "AveragingOptions", "GlobalRotations", "GRRMOptions", "GRRMProblem",
           "average_rotations", "build_problem", "optimize_rotations"]


@dataclass(frozen=True)
class AveragedRotations:
    rotations: dict  #: {view_id: R_cam_from_world} of the views connected to ``fixed_view``
    edge_residual_deg: dict  #: {(i, j): angle of R_j^T R_ij R_i after averaging}
    outliers: list  #: edges whose residual exceeds ``options.max_inlier_residual_deg``
    unregistered: list  #: views not connected to ``fixed_view``
    iterations: int  #: L1 + IRLS iterations
    converged: bool  #: IRLS converged


def average_rotations(relative_rotations: Mapping, weights: Mapping | None = None, fixed_view=None,
                      options: AveragingOptions = AveragingOptions()) -> AveragedRotations:
    """Robust rotation averaging (Chatterjee & Govindu L1 + IRLS, algorithms.md §2) of
    ``relative_rotations`` {(i, j): R_j_from_i}, weighted by ``weights`` {(i, j): w > 0} (e.g.
    inlier counts; default 1). ``fixed_view`` (default: the smallest id) keeps R = I. One
    solve: `rotonly run` filters the outliers and solves again (stages/average.py)."""
    keys = list(relative_rotations)
    for key in keys:
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] != key[1]):
            raise ValueError(f"relative_rotations: keys must be pairs (i, j) of two views, got {key!r}")
    view_ids = sorted({v for key in keys for v in key})
    if fixed_view is None and view_ids:
        fixed_view = view_ids[0]
    if fixed_view not in view_ids:
        raise ValueError(f"fixed_view: {fixed_view!r} is not a view of relative_rotations")
    index = {v: k for k, v in enumerate(view_ids)}
    R = pg.as_rotations(np.stack([np.asarray(relative_rotations[key], dtype=float) for key in keys])
                        if keys else np.zeros((0, 3, 3)), "relative_rotations")
    w = None
    if weights is not None:
        missing = [key for key in keys if key not in weights]
        if missing:
            raise ValueError(f"weights: no weight for the edges {missing[:5]}")
        w = np.array([weights[key] for key in keys], dtype=float)
    result = _average_rotations(len(view_ids), np.array([index[i] for i, _ in keys], dtype=np.int64),
                                np.array([index[j] for _, j in keys], dtype=np.int64), R.reshape(-1, 3, 3), w,
                                fixed_view=index[fixed_view], options=options)
    return AveragedRotations(
        rotations={v: result.R_cam_from_world[k] for v, k in index.items() if result.registered[k]},
        edge_residual_deg={key: float(r) for key, r in zip(keys, result.edge_residual_deg)},
        outliers=[key for key, r, inlier in zip(keys, result.edge_residual_deg, result.inlier_mask)
                  if np.isfinite(r) and not inlier],
        unregistered=[v for v, k in index.items() if not result.registered[k]],
        iterations=result.iterations, converged=bool(result.irls_converged))


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
    for v in view_ids:
        if v not in observations:
            raise ValueError(f"observations: no keypoints of view {v!r}")
        points = np.asarray(observations[v], dtype=float)
        if points.ndim == 2 and points.shape[1] in (2, 3) and len(points):
            points = np.concatenate([points, np.ones((len(points), 1))], axis=1) if points.shape[1] == 2 else points
            refuse_pixels(points[:64], np.array([0, min(len(points), 64)]), f"observations[{v!r}]", single=True)
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
