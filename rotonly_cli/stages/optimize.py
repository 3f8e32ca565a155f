"""Stage `optimize`: GRRM (paper Alg. 3-4) on the averaged rotations.

GRRM's residuals need each edge's closed-form translation, so only active REGULAR edges
enter (PURE_ROTATION and ROTATION_SINGULAR edges are kept out of GRRM: geometry/identification.py).
The problem is the largest connected component of those edges; its first view is the gauge.
Views outside it keep their averaged rotations. Observation ids: (view, keypoint) numbered
by a per-view offset, so every match of every edge through that keypoint shares the id.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.grrm import GRRMOptions, optimize_global_rotations
from rotonly_cli.geometry.pairwise import EdgeBatch, ObservedMatches
from rotonly_cli.scene.view_graph import ViewGraph, largest_component_of, regular_edges, view_index

logger = logging.getLogger(__name__)


@dataclass
class GRRMInputs:
    """What GRRM takes from the view graph: the largest component of the active REGULAR edges
    between views with a rotation, in array form (views in sorted-id order, the first fixed)."""

    views: list[int]  #: view ids, in GRRM's row order
    edges: list[int]  #: graph edge indices, in GRRM's edge order
    edge_views: np.ndarray  #: (E, 2) rows of ``views``
    #: the matches: every keypoint of ``views`` once (their normalized coordinates, view by
    #: view) and each match's two rows there, which are also its observation ids
    matches: ObservedMatches
    obs_ids: np.ndarray  #: (M, 2) observation ids (per-view keypoint offset + keypoint)

    @property
    def batch(self) -> EdgeBatch:
        """The matches as an EdgeBatch (48 bytes per match more than ``matches``: for the
        small problems of the refutation test and the research probes)."""
        return self.matches.subset(np.arange(self.matches.num_edges))


def grrm_inputs(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray
                ) -> GRRMInputs | None:
    """:class:`GRRMInputs` of the graph at these rotations; None without a REGULAR edge."""
    index = view_index(graph)
    registered = {v for v, row in index.items() if np.all(np.isfinite(R_cam_from_world[row]))}
    edges = [k for k in regular_edges(graph) if graph.edges[k].i in registered and graph.edges[k].j in registered]
    if not edges:
        return None
    # the largest component of the REGULAR edges
    touched = sorted({v for k in edges for v in (graph.edges[k].i, graph.edges[k].j)})
    views = largest_component_of(touched, [(graph.edges[k].i, graph.edges[k].j) for k in edges])
    in_component = set(views)
    edges = [k for k in edges if graph.edges[k].i in in_component]
    local = {v: r for r, v in enumerate(views)}
    edge_views = np.array([[local[graph.edges[k].i], local[graph.edges[k].j]] for k in edges], dtype=np.int64)
    sizes_kp = np.array([len(normalized[v]) for v in views], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(sizes_kp)])
    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    bounds = np.concatenate([[0], np.cumsum(counts)])
    # filled edge by edge (no list of copies); int32 rows of the coordinate table (8 bytes per match) where it fits
    obs_ids = np.empty((int(bounds[-1]), 2), dtype=np.int32 if offset[-1] < 2**31 else np.int64)
    for k, m0, m1 in zip(edges, bounds[:-1], bounds[1:]):
        obs_ids[m0:m1, 0] = offset[local[graph.edges[k].i]] + graph.edges[k].matches[:, 0]
        obs_ids[m0:m1, 1] = offset[local[graph.edges[k].j]] + graph.edges[k].matches[:, 1]
    coords = np.concatenate([normalized[v] for v in views])
    if coords.shape[1] == 2:  # z = 1 coordinates
        coords = np.hstack([coords, np.ones((len(coords), 1))])
    return GRRMInputs(views, edges, edge_views, ObservedMatches(coords.astype(float), obs_ids, bounds), obs_ids)


def optimize_graph(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                   options=None, on_iteration=None, jobs: int = 1) -> tuple[np.ndarray, dict]:
    """GRRM-refined copy of ``R_cam_from_world`` (sorted-view-id rows); report with costs.
    ``on_iteration``: called after each GRRM iteration; ``jobs``: processes
    (optimize_global_rotations)."""
    start = time.perf_counter()
    R_out = np.array(R_cam_from_world, dtype=float, copy=True)
    options = options or GRRMOptions()
    index = view_index(graph)
    registered = {v for v, row in index.items() if np.all(np.isfinite(R_out[row]))}
    inputs = grrm_inputs(graph, normalized, R_out)
    if inputs is None:
        return R_out, {"skipped": "no REGULAR edge", "time_s": time.perf_counter() - start}
    views, edges, batch = inputs.views, inputs.edges, inputs.matches
    R0 = np.stack([R_out[index[v]] for v in views])
    from rotonly_cli.runtime.parallel import helper_class

    # half of every linearisation in a forked child where that is safe and pays (same numbers)
    peer_class = helper_class(batch.num_matches, jobs)
    try:
        with np.errstate(all="ignore"):
            result = optimize_global_rotations(R0, inputs.edge_views, batch, inputs.obs_ids, fixed_view=0,
                                               options=options, on_iteration=on_iteration, peer_class=peer_class)
    except ValueError as exc:
        raise AlgorithmError(f"GRRM failed: {exc}") from exc
    from rotonly_cli.geometry import so3

    change = np.degrees(so3.geodesic_angle(result.R_cam_from_world, R0))
    for r, v in enumerate(views):
        R_out[index[v]] = result.R_cam_from_world[r]
    report = {"num_views": len(views), "num_edges": len(edges), "num_matches": batch.num_matches,
              "cost_before": float(result.initial_cost), "cost_after": float(result.cost),
              "iterations": int(result.iterations), "converged": bool(result.converged),
              "rotation_change_deg": {"mean": float(change.mean()), "max": float(change.max())},
              "views_kept_averaged": sorted(registered - set(views)),
              "history": list(result.history), "processes": int(result.processes),
              "start": result.start, "descents": int(result.descents),
              "time_s": time.perf_counter() - start}
    logger.info("optimize (GRRM): %d views, %d edges, cost %.6g -> %.6g in %d iterations, mean change %.4f deg",
                len(views), len(edges), result.initial_cost, result.cost, result.iterations, change.mean())
    return R_out, report
