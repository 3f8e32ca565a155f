"""Stage `translate`: camera centres by LiGT from the global rotations and the tracks of the
active REGULAR edges (PURE_ROTATION edges carry no translation information, paper
§"Scene Identification"). Views LiGT cannot constrain get NaN centres (not registered)."""

from __future__ import annotations

import logging
import time

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.ligt import LiGTOptions, ligt_translations
from rotonly_cli.geometry.tracks import build_tracks, gather_observations
from rotonly_cli.scene.view_graph import ViewGraph, edge_batch, regular_edges, view_index

logger = logging.getLogger(__name__)


#: matches whose robust TRRM weight 1/(1 + s/c²) at the global rotations is below this
#: (residual > √3 c ≈ 7.7 robust sigmas, c = 3 x 1.4826 x the edge's median) are wrong
#: correspondences; LiGT and triangulation have no robust loss of their own, so they are
#: left out of the tracks (measured on Strecha from the COLMAP databases: mean position
#: error entry-P10 0.45 -> 0.033, fountain-P11 0.0057 -> 0.0041, Herz-Jesus-P8 0.0041 -> 0.0035)
MIN_MATCH_WEIGHT = 0.25


#: per-edge keep masks of the last global rotations: translate and triangulate ask for the
#: same edges at the same rotations, so the robust weights are computed once per edge
_KEEP_CACHE: dict[tuple, np.ndarray] = {}


#: [key, Tracks] of the last graph_tracks call (Tracks is immutable)
_LAST_TRACKS: list = []


def inlier_matches(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int],
                   R_cam_from_world: np.ndarray, min_match_weight: float = MIN_MATCH_WEIGHT) -> list[np.ndarray]:
    """The matches of ``edges`` without gross outliers at the global rotations."""
    from rotonly_cli.geometry.trrm import TRRMOptions, robust_match_weights

    matches = [graph.edges[k].matches for k in edges]
    if min_match_weight <= 0 or not edges:
        return matches
    index = view_index(graph)
    R_ij = {k: R_cam_from_world[index[graph.edges[k].j]] @ R_cam_from_world[index[graph.edges[k].i]].T
            for k in edges}
    key = {k: (graph.edges[k].i, graph.edges[k].j, hash(graph.edges[k].matches.tobytes()), R_ij[k].tobytes(),
               min_match_weight) for k in edges}
    missing = [k for k in edges if key[k] not in _KEEP_CACHE]
    if missing:
        if len(_KEEP_CACHE) > 100_000:
            _KEEP_CACHE.clear()
        batch = edge_batch(graph, normalized, missing)
        R = np.stack([R_ij[k] for k in missing])
        with np.errstate(all="ignore"):
            w = robust_match_weights(R, batch, None, TRRMOptions())
            w = robust_match_weights(R, batch, w, TRRMOptions())
        for row, k in enumerate(missing):
            keep = w[batch.offsets[row]:batch.offsets[row + 1]] >= min_match_weight
            _KEEP_CACHE[key[k]] = keep if keep.sum() >= 6 else np.ones_like(keep)
    return [m[_KEEP_CACHE[key[k]]] for k, m in zip(edges, matches)]


def graph_tracks(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int],
                 R_cam_from_world: np.ndarray | None = None):
    """(Tracks in sorted-view-id row space, (N_obs, 2) normalized observations) of ``edges``;
    with the global rotations, gross outlier matches are left out (MIN_MATCH_WEIGHT)."""
    index = view_index(graph)
    matches = [graph.edges[k].matches for k in edges] if R_cam_from_world is None else \
        inlier_matches(graph, normalized, edges, R_cam_from_world)
    pair_keys = [(index[graph.edges[k].i], index[graph.edges[k].j]) for k in edges]
    # translate and triangulate usually ask for the same tracks (no PURE_ROTATION edge):
    # the last ones are kept, keyed by the pairs and their matches
    key = (len(index), tuple(pair_keys), tuple(hash(m.tobytes()) for m in matches),
           tuple(m.shape[0] for m in matches))
    if _LAST_TRACKS and _LAST_TRACKS[0] == key:
        tracks = _LAST_TRACKS[1]
    else:
        tracks = build_tracks(pair_keys, matches)
        _LAST_TRACKS[:] = [key, tracks]
    per_view = [normalized.get(v, np.zeros((0, 2))) for v in graph.view_ids()]
    return tracks, gather_observations(tracks, per_view)


def translate_graph(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                    options: LiGTOptions | None = None) -> tuple[np.ndarray, dict]:
    """(centres (n, 3), NaN where unknown; report)."""
    start = time.perf_counter()
    index = view_index(graph)
    registered = np.all(np.isfinite(R_cam_from_world.reshape(len(index), -1)), axis=1)
    edges = [k for k in regular_edges(graph) if registered[index[graph.edges[k].i]]
             and registered[index[graph.edges[k].j]]]
    if not edges:
        raise AlgorithmError("translation: no REGULAR edge between registered views (all pure rotation?)")
    R = np.where(registered[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, normalized, edges, R)
    result = ligt_translations(R, tracks.track_id, tracks.view, obs_xy, view_mask=registered, options=options)
    centers = np.where(result.has_translation[:, None], result.centers, np.nan)
    ids = graph.view_ids()
    without = [ids[r] for r in np.flatnonzero(registered & ~result.has_translation)]
    report = {"num_edges": len(edges), "num_tracks": tracks.num_tracks, "num_observations": tracks.num_observations,
              "num_inconsistent_tracks": tracks.num_inconsistent,
              "num_views_with_centre": int(result.has_translation.sum()),
              "views_without_centre": without, "smallest_eigenvalues": result.smallest_eigenvalues.tolist(),
              "sign_votes": list(result.sign_votes), "time_s": time.perf_counter() - start}
    logger.info("translate (LiGT): %d tracks from %d REGULAR edges, %d views with a centre%s",
                tracks.num_tracks, len(edges), report["num_views_with_centre"],
                f", {len(without)} without" if without else "")
    return centers, report
