"""Stage `average`: robust rotation averaging (L1 + IRLS) of the active edges, weighted by
inlier count, with the gross-outlier filter.

Edges whose residual angle after averaging exceeds ``max_residual_deg`` are filtered
("rotation averaging outlier"), the largest component is re-checked and the averaging is
solved again without them, until no edge is removed (at most ``max_rounds``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.averaging import AveragingOptions, average_rotations
from rotonly_cli.options import AverageOptions
from rotonly_cli.scene.view_graph import (
    ViewGraph,
    active_bridges,
    edge_residuals_deg,
    largest_component,
    regular_edges,
    view_index,
)
from rotonly_cli.stages import listed

logger = logging.getLogger(__name__)
OUTLIER_REASON = "rotation averaging outlier"


def _solve(graph: ViewGraph, index: dict[int, int], averaging: AveragingOptions):
    """One averaging of the active edges of the largest component; (edge list, result)."""
    component = largest_component(graph)
    edges = graph.active_edges()
    if len(component) < 2:
        raise AlgorithmError("rotation averaging: fewer than two connected views left")
    e_i = np.array([index[graph.edges[k].i] for k in edges])
    e_j = np.array([index[graph.edges[k].j] for k in edges])
    R_ij = np.stack([graph.edges[k].R_j_from_i for k in edges])
    weights = np.array([graph.edges[k].num_inliers for k in edges], dtype=float)
    result = average_rotations(len(index), e_i, e_j, R_ij, weights, fixed_view=index[component[0]],
                               options=averaging)
    return edges, result


def average_graph(graph: ViewGraph, options: AverageOptions = AverageOptions()) -> tuple[np.ndarray, dict]:
    """(R_cam_from_world (n, 3, 3) in sorted-view-id order, NaN outside the component; report)."""
    start = time.perf_counter()
    index = view_index(graph)
    n = len(index)
    averaging = replace(options.averaging, max_inlier_residual_deg=options.max_residual_deg)
    rounds, num_outliers = [], 0
    R = np.full((n, 3, 3), np.nan)
    for _ in range(max(options.max_rounds, 1)):
        edges, result = _solve(graph, index, averaging)
        R = result.R_cam_from_world
        for row, k in enumerate(edges):
            graph.edges[k].residual_deg = float(result.edge_residual_deg[row])
        outliers = [k for row, k in enumerate(edges) if not result.inlier_mask[row]]
        residual = result.edge_residual_deg[np.isfinite(result.edge_residual_deg)]
        rounds.append({"num_edges": len(edges), "num_outliers": len(outliers),
                       "residual_deg_median": float(np.median(residual)) if residual.size else None,
                       "residual_deg_max": float(residual.max()) if residual.size else None,
                       "irls_iterations": int(result.irls_iterations), "irls_converged": bool(result.irls_converged),
                       "irls_sigma_deg": float(result.irls_sigma_deg)})
        if not outliers:
            break
        for k in outliers:
            graph.edges[k].filter(OUTLIER_REASON)
        num_outliers += len(outliers)
        logger.info("average: %d outlier edges (residual > %.3g deg) filtered, solving again", len(outliers),
                    options.max_residual_deg)
    else:  # the last round still removed edges: solve once more on the survivors
        R = _solve(graph, index, averaging)[1].R_cam_from_world
    component = set(largest_component(graph))
    for v, row in index.items():
        if v not in component:
            R[row] = np.nan
    report = {"rounds": rounds, "num_outliers_filtered": num_outliers, "num_active_edges": len(graph.active_edges()),
              "num_registered_views": len(component), "unregistered_views": list(graph.unregistered_views),
              "max_residual_deg": options.max_residual_deg, "time_s": time.perf_counter() - start}
    logger.info("average: %d views registered, %d outlier edges filtered in %d round(s)", len(component),
                num_outliers, len(rounds))
    return R, report


def unchecked_edges(graph: ViewGraph, registered: set[int]) -> list[tuple[int, int]]:
    """The active edges between ``registered`` views that no cycle of those edges runs through
    (bridges): the rotation between their two sides is that pair's two-view estimate alone, and
    neither the averaging's residuals nor GRRM can tell a wrong one. None with fewer than three
    registered views (two views have nothing else to check against)."""
    if len(registered) < 3:
        return []
    return [(graph.edges[k].i, graph.edges[k].j) for k in active_bridges(graph, registered)]


def unchecked_edges_warning(edges: list[tuple[int, int]], max_shown: int = 8) -> str | None:
    """The run summary's warning for :func:`unchecked_edges`; None without any."""
    if not edges:
        return None
    shown = listed((f"{i}-{j}" for i, j in edges), max_shown)
    return (f"{len(edges)} pair(s) of the view graph lie on no cycle (edges {shown}): the rotation across each "
            f"rests on that pair's two-view estimate alone, which nothing checks; images overlapping both sides "
            f"would close cycles (reports/run.json: edges_on_no_cycle)")


#: the run warns when the median of :func:`pair_residuals_deg` is above this (deg): the mean
#: rotation error follows that median, and above it a bundle adjustment of rotonly's model cuts
#: the error by a third or more (docs/tuning.md "Pair scatter")
PAIR_SCATTER_WARN_DEG = 0.1


def pair_residuals_deg(graph: ViewGraph, R_cam_from_world: dict[int, np.ndarray]) -> np.ndarray:
    """Angle (deg) between each active REGULAR edge's own relative rotation (TRRM's, the pair
    alone) and the one the final rotations imply, R_j R_iᵀ, over the edges between views in
    ``R_cam_from_world`` (view id -> rotation). Each pair's translation is free in TRRM and in
    GRRM, so where it is poorly fixed (few matches, noisy or low-resolution keypoints) the
    pairs scatter about the global solution, and the rotations are uncertain at that level."""
    return edge_residuals_deg([graph.edges[k] for k in regular_edges(graph)
                               if graph.edges[k].i in R_cam_from_world and graph.edges[k].j in R_cam_from_world],
                              R_cam_from_world)


def pair_scatter_deg(graph: ViewGraph, poses: dict) -> float | None:
    """Median of :func:`pair_residuals_deg` at ``poses`` (view id -> Pose, the outputs'); None
    without a REGULAR edge between them (reports/run.json: pair_residual_deg_median)."""
    residuals = pair_residuals_deg(graph, {v: pose.R_cam_from_world for v, pose in poses.items()})
    return float(np.median(residuals)) if residuals.size else None


def pair_scatter_warning(median_deg: float | None) -> str | None:
    """The run summary's warning when the pairs' rotations scatter by more than
    PAIR_SCATTER_WARN_DEG (median of :func:`pair_residuals_deg`); None below it."""
    if median_deg is None or not median_deg > PAIR_SCATTER_WARN_DEG:
        return None
    return (f"the pairs' own relative rotations scatter by a median {median_deg:.2f} deg about the global rotations "
            f"(few matches per pair, noisy or low-resolution keypoints): expect rotation errors of that order; a "
            f"bundle adjustment of OUT/sparse (colmap bundle_adjuster) tightens them (reports/run.json: "
            f"pair_residual_deg_median; view_graph.json: each edge's residual_deg)")
