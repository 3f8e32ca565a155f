"""Stage `reject`: multi-view outlier rejection under the global poses.

A wrong match that two-view RANSAC accepted (repeated structure a few pixels off its
epipolar line) fits its own pair's geometry, which it helped estimate, but not the epipolar
geometry E_ij = [t_ij]x R_ij that the global rotations and the LiGT centres give that pair
(t_ij = R_j (c_i - c_j)): every pose there is fixed by all the other edges. Matches whose
Sampson error under it exceeds max(``outlier_sigmas`` x sigma, ``min_threshold_px``) (sigma =
1.4826 x the median over all matches, in pixels) are dropped (an edge that would keep fewer
than ``min_inliers`` keeps them all), and the edges' rotations are checked against the global
ones again. The
pipeline then runs GRRM and LiGT on what is left, until a round drops nothing
(pipeline.reject_stage).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.tracks import Tracks
from rotonly_cli.options import RejectOptions
from rotonly_cli.runtime import cluster, heartbeat
from rotonly_cli.scene.view_graph import (
    ViewGraph,
    active_bridges,
    edge_arrays,
    edge_residuals_deg,
    largest_component,
    regular_edges,
    view_index,
)
from rotonly_cli.stages import listed

logger = logging.getLogger(__name__)
DROP_REASON = "inconsistent with the global poses"
RESIDUAL_REASON = "rotation residual after multi-view rejection"
CONFIRM_REASON = "not in a track of three or more views"
REFUTE_REASON = "refuted by the other pairs (leave-one-out)"
#: the leave-one-out test inverts its 3n x 3n normal matrix densely: beyond this many views it
#: is not run (1000 views, 10 000 pairs: 1.5 s, 216 MB peak)
REFUTE_MAX_VIEWS = 1000
#: an edge keeps only its confirmed matches when they over-determine its relative pose (one
#: more than the five-point sample); with fewer it has no evidence either way and keeps all
MIN_CONFIRMED = 6


def undone_round_warning(report: dict | None) -> str | None:
    """The run summary's warning when a rejection round was undone because its re-solve left
    views without a centre or put them off their baselines (reports/reject.json): tracks tie
    those views to the rest so weakly that dropping a few hundred matches cuts them loose, and
    their poses are the least certain of the run. None otherwise."""
    for round_ in (report or {}).get("rounds") or []:
        undone = round_.get("undone")
        if not undone:
            continue
        lost = undone.get("views_without_centre", [])
        views = map(str, sorted({int(v) for v in [*lost, *undone.get("views_off", [])]}))  # both lists hold view ids
        failure = "could not place them" if lost else "put them off their pairs' baselines"
        return (f"view(s) {listed(views)} are tied to the rest by few tracks: without the {round_['num_dropped']} "
                f"matches inconsistent with the global poses, LiGT {failure}, so those matches "
                f"were kept (reports/reject.json); these views' poses are the least certain of this run and may "
                f"change with --seed; images overlapping them and the rest would tie them in")
    return None


def confirmation_warning(report: dict | None) -> str | None:
    """The run summary's warning when the reject stage's confirmation by tracks was kept
    (reports/reject.json: ``confirmation``): the pairs held wrong matches that fit their own
    epipolar geometry (repeated structure, most likely) and had bent the rotations until the
    tracks refuted them. The run's rotations are the corrected ones, but such an input's are
    the least certain; None otherwise."""
    confirmation = (report or {}).get("confirmation")
    if not confirmation or confirmation.get("undone") or not confirmation.get("rounds"):
        return None
    before, after = confirmation["first_solve_sigma_px"]
    left = confirmation.get("views_left_out_before") or []
    return (f"the tracks refuted the rotations the pairs' matches gave (LiGT's first solve {before:.3g} px off the "
            f"tracks{f', view(s) {listed(map(str, left))} left out' if left else ''}): pairs hold wrong matches "
            f"that fit their own epipolar geometry, repeated structure most likely; the rotations were solved again "
            f"on the matches a third view confirms ({after:.3g} px off; reports/reject.json: confirmation)")


def refutation_warning(report: dict | None) -> str | None:
    """The run summary's warning when the reject stage filtered pairs that the other pairs
    refute (reports/reject.json: ``refutation``); None otherwise."""
    kept = [r for r in ((report or {}).get("refutation") or {}).get("rounds", []) if r.get("kept")]
    if not kept:
        return None
    pairs = listed(f"{r['edge'][0]}-{r['edge'][1]} ({r['fit_ratio']:.3g}x)" for r in kept)
    return (f"pair(s) {pairs} refuted by the other pairs: their matches fit the rotation the others imply that many "
            f"times worse than their own, wrong matches that fit their own epipolar geometry (repeated structure, "
            f"most likely); filtered (reports/reject.json: refutation, view_graph.json)")


def refuted_edges(graph: ViewGraph, inputs, R_cam_from_world: np.ndarray) -> list[dict]:
    """GRRM's edges (``inputs``: stages.optimize.grrm_inputs of ``graph``) with the
    leave-one-out test of geometry.refutation under the rotations ``R_cam_from_world`` (rows
    of ``graph.view_ids()``), the most refuted first: per edge its index, views, fit ratio
    and the rotation change without it (deg). Bridges are not tested."""
    from rotonly_cli.geometry.refutation import leave_one_out

    if inputs is None or len(inputs.edges) < 2:
        return []
    if len(inputs.views) > REFUTE_MAX_VIEWS:
        logger.info("reject: %d views, beyond the leave-one-out test's %d: not tested", len(inputs.views),
                    REFUTE_MAX_VIEWS)
        return []
    index = view_index(graph)
    bridges = set(active_bridges(graph, set(inputs.views)))
    test = leave_one_out(np.stack([R_cam_from_world[index[v]] for v in inputs.views]), inputs.edge_views,
                         np.stack([graph.edges[k].R_j_from_i for k in inputs.edges]), inputs.batch,
                         skip=np.array([k in bridges for k in inputs.edges]))
    found = [{"edge_index": k, "edge": [graph.edges[k].i, graph.edges[k].j], "fit_ratio": float(ratio),
              "rotation_change_deg": float(change)}
             for k, ratio, change in zip(inputs.edges, test.fit_ratio, test.change_deg) if np.isfinite(ratio)]
    return sorted(found, key=lambda entry: -entry["fit_ratio"])


def reject_round(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                 centers: np.ndarray, focal_px: np.ndarray, options: RejectOptions, min_inliers: int,
                 max_residual_deg: float) -> dict:
    """One round (module docstring) on the REGULAR edges between posed views, in place;
    ``min_inliers`` and ``max_residual_deg``: the run's LoadOptions.min_inliers and
    AverageOptions.max_residual_deg. Returns the round's report (counts and threshold)."""
    start = time.perf_counter()
    heartbeat.advance()  # the reject stage's rounds, for the progress lines in a pipe
    index = view_index(graph)
    posed = np.all(np.isfinite(R_cam_from_world.reshape(len(index), -1)), axis=1) & np.all(np.isfinite(centers), axis=1)
    edges = [k for k in regular_edges(graph) if posed[index[graph.edges[k].i]] and posed[index[graph.edges[k].j]]]
    # every edge's errors are a slice of one array (no list of per-edge arrays beside their
    # concatenation)
    offsets = np.cumsum([0] + [graph.edges[k].matches.shape[0] for k in edges])
    every = np.empty(int(offsets[-1]))
    errors = [every[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
    session = cluster.active()
    if session is not None and edges:  # --cluster: tasks of consecutive edges (runtime/cluster.py)
        _cluster_errors(session, graph, normalized, edges, _edge_geometry(graph, edges, index, R_cam_from_world,
                                                                           centers, focal_px), every)
    for k, error in zip(edges, errors if session is None else ()):
        edge = graph.edges[k]
        i, j = index[edge.i], index[edge.j]
        R_ij = R_cam_from_world[j] @ R_cam_from_world[i].T
        t_ij = R_cam_from_world[j] @ (centers[i] - centers[j])
        norm = np.linalg.norm(t_ij)
        x_i = normalized[edge.i][edge.matches[:, 0]]
        x_j = normalized[edge.j][edge.matches[:, 1]]
        scale = 0.5 * (focal_px[i] + focal_px[j])
        error[:] = pg.sampson_errors(R_ij, t_ij / norm, x_i, x_j) * scale if norm > 0 else 0.0
    report = {"num_edges": len(edges), "num_matches": int(every.size), "num_dropped": 0,
              "sigma_px": None, "threshold_px": None, "edges_filtered": {}}
    if not errors or report["num_matches"] == 0:
        return report
    sigma = 1.4826 * float(np.median(every))
    threshold = max(options.outlier_sigmas * sigma, options.min_threshold_px)
    filtered: dict[str, int] = {}
    # the view-graph check of the averaging, at the optimised rotations
    residuals = edge_residuals_deg([graph.edges[k] for k in edges],
                                   {v: R_cam_from_world[row] for v, row in index.items() if posed[row]})
    for k, error, residual in zip(edges, errors, residuals):
        edge = graph.edges[k]
        keep = error <= threshold
        if np.count_nonzero(keep) < min_inliers:
            # an edge this round would empty keeps its matches: filtering it can cut a weakly
            # connected view loose, and LiGT's centre for it with it
            report["edges_kept_whole"] = report.get("edges_kept_whole", 0) + 1
            continue
        report["num_dropped"] += edge.drop_matches(keep, DROP_REASON)
        edge.residual_deg = float(residual)
        if edge.residual_deg > max_residual_deg:
            edge.filter(RESIDUAL_REASON)
            filtered[RESIDUAL_REASON] = filtered.get(RESIDUAL_REASON, 0) + 1
    largest_component(graph)
    report.update(sigma_px=sigma, threshold_px=threshold, edges_filtered=filtered, time_s=time.perf_counter() - start)
    return report


#: matches per --cluster task of the round's Sampson errors (~0.1 us each)
CLUSTER_TASK_MATCHES = 1 << 22


def _edge_geometry(graph: ViewGraph, edges: list[int], index: dict, R_cam_from_world: np.ndarray,
                   centers: np.ndarray, focal_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per edge, as :func:`reject_round`'s own loop makes them: R_ij (E, 3, 3), the unit
    t_ij (E, 3; zero without a baseline) and the pixel scale (E,)."""
    R, t, scale = np.empty((len(edges), 3, 3)), np.zeros((len(edges), 3)), np.zeros(len(edges))
    for row, k in enumerate(edges):
        edge = graph.edges[k]
        i, j = index[edge.i], index[edge.j]
        R[row] = R_cam_from_world[j] @ R_cam_from_world[i].T
        t_ij = R_cam_from_world[j] @ (centers[i] - centers[j])
        norm = np.linalg.norm(t_ij)
        if norm > 0:
            t[row] = t_ij / norm
        scale[row] = 0.5 * (focal_px[i] + focal_px[j])
    return R, t, scale


def _cluster_errors(session, graph: ViewGraph, normalized: dict, edges: list[int], geometry: tuple,
                    every: np.ndarray) -> None:
    """The Sampson errors (px) of ``edges``' matches into ``every``, on the cluster: tasks of
    consecutive edges of CLUSTER_TASK_MATCHES matches or more, the keypoints scattered once."""
    from rotonly_cli.runtime.cluster import group_ranges

    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    groups = [(g[0][0], g[-1][1]) for g in group_ranges([(k, k + 1) for k in range(len(edges))], counts,
                                                        CLUSTER_TASK_MATCHES)]
    keypoints = session.scatter(normalized, "reject")
    tasks = ((keypoints, edge_arrays(graph, edges[a:b]), *(part[a:b] for part in geometry)) for a, b in groups)
    every[:] = np.concatenate(session.map("reject", _errors_task, tasks, len(groups)))


def _errors_task(normalized: dict, arrays: tuple, R: np.ndarray, t: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """On a cluster worker: :func:`reject_round`'s Sampson errors of a task's edges."""
    views, counts, matches = arrays
    bounds = np.concatenate([[0], np.cumsum(counts)])
    errors = np.empty(int(bounds[-1]))
    for k in range(len(views)):
        pair = matches[bounds[k]:bounds[k + 1]]
        x_i, x_j = normalized[int(views[k, 0])][pair[:, 0]], normalized[int(views[k, 1])][pair[:, 1]]
        errors[bounds[k]:bounds[k + 1]] = pg.sampson_errors(R[k], t[k], x_i, x_j) * scale[k] \
            if t[k].any() else 0.0
    return errors


def confirmed_matches(graph: ViewGraph, tracks: Tracks, edges: list[int], min_views: int = 3) -> list[np.ndarray]:
    """Per edge of ``edges`` (m,) bool: the matches whose two keypoints are observations of
    one track of ``tracks`` (the triangulation's kept tracks, views as rows of
    ``graph.view_ids()``) that holds at least ``min_views`` views. A third view confirms
    such a match: its point reprojects within the outlier test there too. One sorted key
    per observation (view row, keypoint), looked up for every match at once."""
    index = view_index(graph)
    long_track = tracks.length[tracks.track_id] >= min_views
    stride = 1 + max([int(tracks.feature.max(initial=0))]
                     + [int(graph.edges[k].matches.max(initial=0)) for k in edges])
    keys = tracks.view[long_track] * stride + tracks.feature[long_track]
    order = np.argsort(keys)
    keys, track_ids = keys[order], tracks.track_id[long_track][order]
    if not keys.size:
        return [np.zeros(len(graph.edges[k].matches), dtype=bool) for k in edges]
    # one key per match end, filled edge by edge (no per-edge row / keypoint lists beside it)
    query = np.empty(2 * sum(len(graph.edges[k].matches) for k in edges), dtype=np.int64)
    start = 0
    for k in edges:
        edge = graph.edges[k]
        for v, column in ((edge.i, 0), (edge.j, 1)):
            m = len(edge.matches)
            np.add(edge.matches[:, column], index[v] * stride, out=query[start:start + m], dtype=np.int64,
                   casting="unsafe")
            start += m
    at = np.minimum(np.searchsorted(keys, query), keys.size - 1)
    track_of = np.where(keys[at] == query, track_ids[at], -1)
    confirmed, start = [], 0
    for k in edges:  # per edge: its i-side keypoints, then its j-side ones
        m = len(graph.edges[k].matches)
        track_i, track_j = track_of[start:start + m], track_of[start + m:start + 2 * m]
        confirmed.append((track_i >= 0) & (track_i == track_j))
        start += 2 * m
    return confirmed


def confirm_round(original: ViewGraph, confirmed: list[np.ndarray], edges: list[int]) -> tuple[ViewGraph, dict]:
    """A copy of ``original`` whose ``edges`` keep only their ``confirmed`` matches
    (:func:`confirmed_matches`), but for the edges with fewer than MIN_CONFIRMED and the
    bridges (no cycle runs through them: the rotation across one is its own pair's estimate
    whatever the others say, so fewer matches only make it noisier), which keep all of
    their own; and the round's counts."""
    graph = original.copy()
    report = {"num_edges": len(edges), "num_matches": 0, "num_dropped": 0, "edges_kept_whole": 0}
    bridges = set(active_bridges(original))
    for k, keep in zip(edges, confirmed):
        report["num_matches"] += int(keep.size)
        if np.count_nonzero(keep) < MIN_CONFIRMED or k in bridges:
            report["edges_kept_whole"] += 1
            continue
        report["num_dropped"] += graph.edges[k].drop_matches(keep, CONFIRM_REASON)
    return graph, report
