"""Tracks of a view graph's matches, shared by the stages of one run.

translate (LiGT) and triangulate ask for the tracks of the same edges at the same global
rotations (unless PURE_ROTATION edges differ between them): a :class:`TrackCache`, owned by
the run (``chain.Run.tracks``), builds them once. Without a cache every call builds afresh.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from rotonly_cli.geometry.tracks import Tracks, build_tracks, gather_observations
from rotonly_cli.scene.view_graph import ViewGraph, edge_batch, view_index

#: matches whose robust TRRM weight 1/(1 + s/c²) at the global rotations is below this
#: (residual > √3 c ≈ 7.7 robust sigmas, c = 3 x 1.4826 x the edge's median) are wrong
#: correspondences; LiGT and triangulation have no robust loss of their own, so they are
#: left out of the tracks (docs/tuning.md)
MIN_MATCH_WEIGHT = 0.25


class TrackCache:
    """Per-edge keep masks at the last global rotations and the last tracks built, keyed by
    what they depend on (edges, matches, rotations), so a hit returns the same arrays."""

    def __init__(self) -> None:
        self.keep: dict[tuple, np.ndarray] = {}
        self.last: tuple[tuple, Tracks] | None = None


@dataclass
class MatchWeights:
    """Per-match robust TRRM weights of some edges, in their order (a per-edge result of
    runtime.parallel.map_edge_chunks: its chunks and processes concatenate)."""

    weights: np.ndarray


def robust_weights(R_ij: np.ndarray, batch) -> MatchWeights:
    """The robust TRRM weights (two IRLS rounds, geometry.trrm.irls_match_weights) of the
    matches of ``batch`` at the relative rotations ``R_ij``; an edge's depend on its own
    matches only."""
    from rotonly_cli.geometry.trrm import irls_match_weights

    with np.errstate(all="ignore"):
        return MatchWeights(irls_match_weights(R_ij, batch))


def inlier_matches(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int],
                   R_cam_from_world: np.ndarray, min_match_weight: float = MIN_MATCH_WEIGHT,
                   cache: TrackCache | None = None, weigh: Callable | None = None) -> list[np.ndarray]:
    """The matches of ``edges`` without gross outliers at the global rotations. ``weigh``
    (edges, R_ij (E, 3, 3)) -> :func:`robust_weights` of those edges' matches, concatenated
    (the stages pass one that spreads the edges over processes); None: in this process."""
    matches = [graph.edges[k].matches for k in edges]
    if min_match_weight <= 0 or not edges:
        return matches
    kept = (cache or TrackCache()).keep
    index = view_index(graph)
    R_ij = {k: R_cam_from_world[index[graph.edges[k].j]] @ R_cam_from_world[index[graph.edges[k].i]].T
            for k in edges}
    key = {k: (graph.edges[k].i, graph.edges[k].j, hash(graph.edges[k].matches.tobytes()), R_ij[k].tobytes(),
               min_match_weight) for k in edges}
    missing = [k for k in edges if key[k] not in kept]
    if missing and weigh is not None:
        groups = [(missing, weigh(missing, np.stack([R_ij[k] for k in missing])))]
    else:
        # the weights of an edge depend on its own matches only: a group of edges at a time
        # keeps the TRRM tables (~200 B per match) to one group's matches
        groups = ((group, robust_weights(np.stack([R_ij[k] for k in group]),
                                         edge_batch(graph, normalized, group)).weights)
                  for group in _edge_groups(missing, [graph.edges[k].matches.shape[0] for k in missing]))
    for group, w in groups:
        start = 0
        for k in group:
            stop = start + graph.edges[k].matches.shape[0]
            keep = w[start:stop] >= min_match_weight
            kept[key[k]] = keep if keep.sum() >= 6 else np.ones_like(keep)
            start = stop
    # an edge that keeps every match is passed as it is: no copy of all matches beside the graph's
    return [m if kept[key[k]].all() else m[kept[key[k]]] for k, m in zip(edges, matches)]


#: inlier_matches weighs the matches of about this many at a time (whole edges)
MATCHES_PER_GROUP = 1 << 19


def _edge_groups(edges: list[int], counts: list[int]) -> list[list[int]]:
    """``edges`` in order, cut into consecutive groups of at most MATCHES_PER_GROUP matches
    (``counts`` per edge; an edge with more is a group of its own)."""
    groups: list[list[int]] = []
    total = MATCHES_PER_GROUP
    for k, count in zip(edges, counts):
        if total + count > MATCHES_PER_GROUP:
            groups.append([])
            total = 0
        groups[-1].append(k)
        total += count
    return groups


def graph_tracks(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int],
                 R_cam_from_world: np.ndarray | None = None, cache: TrackCache | None = None,
                 keep_conflicts: bool = False, weigh: Callable | None = None):
    """(Tracks in sorted-view-id row space, (N_obs, 2) normalized observations) of ``edges``;
    with the global rotations, gross outlier matches are left out (MIN_MATCH_WEIGHT).
    ``keep_conflicts``: the components that see a view twice in ``Tracks.conflicts``
    (geometry.tracks.build_tracks); the tracks themselves are the same either way.
    ``weigh``: as for :func:`inlier_matches`."""
    index = view_index(graph)
    matches = [graph.edges[k].matches for k in edges] if R_cam_from_world is None else \
        inlier_matches(graph, normalized, edges, R_cam_from_world, cache=cache, weigh=weigh)
    pair_keys = [(index[graph.edges[k].i], index[graph.edges[k].j]) for k in edges]
    key = (len(index), tuple(pair_keys), tuple(hash(m.tobytes()) for m in matches),
           tuple(m.shape[0] for m in matches))
    if cache is not None and cache.last is not None and cache.last[0] == key and not keep_conflicts:
        tracks = cache.last[1]
    else:
        tracks = build_tracks(pair_keys, matches, keep_conflicts=keep_conflicts)
        if cache is not None:
            # the conflicts (nodes and matches of up to all the tracks) are used once, by the
            # caller that asked for them, and not kept for the rest of the run
            cache.last = (key, replace(tracks, conflicts=None) if keep_conflicts else tracks)
    per_view = [normalized.get(v, np.zeros((0, 2))) for v in graph.view_ids()]
    return tracks, gather_observations(tracks, per_view)


#: Edge.dropped_matches reason of :func:`drop_minority_keypoint_matches`
MINORITY_REASON = "minority keypoint of its track"


def drop_minority_keypoint_matches(graph: ViewGraph, edges: list[int]) -> dict:
    """Drop from ``edges`` the matches on a keypoint of a single match that its track sees in
    the same view through a keypoint of three matches or more
    (geometry.tracks.minority_keypoint_matches). An edge
    that would keep fewer than half its matches keeps them all (the edge filters judge such a
    pair whole). Returns the report: matches looked at, dropped, edges touched."""
    from rotonly_cli.geometry.tracks import minority_keypoint_matches

    edges = [k for k in edges if graph.edges[k].num_inliers]
    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    report = {"num_matches": int(counts.sum()), "num_dropped": 0, "edges_touched": 0}
    if not edges:
        return report
    num_feats = max(int(graph.edges[k].matches.max()) for k in edges) + 1
    bounds = np.concatenate([[0], np.cumsum(counts)])
    keys = np.empty((int(bounds[-1]), 2), dtype=np.int64)  # filled edge by edge (no list of copies)
    for k, a, b in zip(edges, bounds[:-1], bounds[1:]):
        edge = graph.edges[k]
        np.add(edge.matches, (edge.i * num_feats, edge.j * num_feats), out=keys[a:b], dtype=np.int64,
               casting="unsafe")
    drop = minority_keypoint_matches(keys, num_feats)
    del keys
    for k, a, b in zip(edges, bounds[:-1], bounds[1:]):
        dropped = int(np.count_nonzero(drop[a:b]))
        if dropped and 2 * dropped <= b - a:
            report["num_dropped"] += graph.edges[k].drop_matches(~drop[a:b], MINORITY_REASON)
            report["edges_touched"] += 1
    return report
