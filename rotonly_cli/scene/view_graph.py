"""View graph of a reconstruction: views, edges with relative poses and per-edge diagnostics,
and the graph queries and filters the stages share.

Data model of architecture.md "Data model". An edge (i, j) holds view ids with i < j,
``R_j_from_i`` / unit ``t_dir`` (= t_ij / ‖t_ij‖, COLMAP ``cam2_from_cam1`` with image1 = i)
and its inlier matches ``matches[:, 0]`` in view i, ``matches[:, 1]`` in view j.

Filters never delete: they set ``status = "filtered"`` with a ``reason`` (first reason wins),
and :func:`largest_component` is re-checked after each filter (architecture.md).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from rotonly_cli.compat import StrEnum
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.identification import SceneKind
from rotonly_cli.scene.types import View


class EdgeStatus(StrEnum):
    ACTIVE = "active"  #: used by the next stage
    FILTERED = "filtered"  #: left out, with a reason (never deleted)


ACTIVE = EdgeStatus.ACTIVE
FILTERED = EdgeStatus.FILTERED
SINGULAR_REASON = "rotation singular (Holoplane / RankRegular-line)"


@dataclass
class Edge:
    i: int  # view id (smaller)
    j: int  # view id (larger)
    R_j_from_i: np.ndarray  # (3, 3)
    t_dir: np.ndarray  # (3,) unit t_ij; zeros when unknown / pure rotation
    matches: np.ndarray  # (m, 2) int64 keypoint indices [view i, view j]
    pose_source: str = ""  # "stored" (COLMAP E), "ransac" (re-estimated), "given"
    config: str | None = None  # the input's two-view configuration (COLMAP name, "E" ...)
    scene_kind: str | None = None  # SceneKind value after identification
    detection_value: float = math.nan  # v_rs (paper §"Scene Identification")
    pure_rotation_ratio: float = math.nan  # ρ = f_pure / f_TRRM
    status: EdgeStatus = ACTIVE
    reason: str = ""
    residual_deg: float = math.nan  # angle of R_jᵀ R_ij R_i after rotation averaging
    trrm_initial_cost: float = math.nan
    trrm_cost: float = math.nan
    trrm_iterations: int = 0
    trrm_rotation_change_deg: float = math.nan
    #: matches removed from this edge, per reason (the input's matches minus ``matches``)
    dropped_matches: dict[str, int] = field(default_factory=dict)

    @property
    def num_inliers(self) -> int:
        return int(self.matches.shape[0])

    @property
    def active(self) -> bool:
        return self.status == ACTIVE

    def filter(self, reason: str) -> None:
        """Mark filtered; an edge keeps the first reason it was filtered for."""
        if self.status == ACTIVE:
            self.status, self.reason = FILTERED, reason

    def drop_matches(self, keep: np.ndarray, reason: str) -> int:
        """Keep the matches where ``keep`` (m,) is True; the others are counted under ``reason``.
        Returns how many were dropped."""
        keep = np.asarray(keep, dtype=bool)
        dropped = int(keep.size - np.count_nonzero(keep))
        if dropped:
            self.matches = self.matches[keep]
            self.dropped_matches[reason] = self.dropped_matches.get(reason, 0) + dropped
        return dropped

    def diagnostics(self) -> dict:
        def number(x: float) -> float | None:  # JSON has no NaN
            return None if x is None or not np.isfinite(x) else float(x)

        return {
            "i": int(self.i), "j": int(self.j), "num_inliers": self.num_inliers,
            "pose_source": self.pose_source, "config": self.config, "scene_kind": self.scene_kind,
            "detection_value": number(self.detection_value),
            "pure_rotation_ratio": number(self.pure_rotation_ratio),
            "status": self.status, "reason": self.reason, "residual_deg": number(self.residual_deg),
            "trrm_initial_cost": number(self.trrm_initial_cost), "trrm_cost": number(self.trrm_cost),
            "trrm_iterations": int(self.trrm_iterations),
            "trrm_rotation_change_deg": number(self.trrm_rotation_change_deg),
            "dropped_matches": dict(sorted(self.dropped_matches.items())),
            "R_j_from_i": np.asarray(self.R_j_from_i, dtype=float).tolist(),
            "t_dir": np.asarray(self.t_dir, dtype=float).tolist(),
        }


@dataclass
class ViewGraph:
    views: dict[int, View] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    #: views outside the largest component of active edges (reported, not registered)
    unregistered_views: list[int] = field(default_factory=list)

    def view_ids(self) -> list[int]:
        return sorted(self.views)

    def copy(self) -> ViewGraph:
        """A deep copy whose edges share their match arrays with this graph's: nothing writes
        into one (Edge.drop_matches rebinds the edge to a new array), and a copy of them
        would cost 16 bytes per match (337 MB at 21 M matches, the reject stage's peak)."""
        return copy.deepcopy(self, {id(edge.matches): edge.matches for edge in self.edges})

    def active_edges(self) -> list[int]:
        return [k for k, edge in enumerate(self.edges) if edge.active]

    def counts(self) -> dict:
        reasons: dict[str, int] = {}
        for edge in self.edges:
            if not edge.active:
                reasons[edge.reason] = reasons.get(edge.reason, 0) + 1
        return {"views": len(self.views), "edges": len(self.edges),
                "active_edges": len(self.active_edges()), "filtered_by_reason": dict(sorted(reasons.items())),
                "unregistered_views": list(self.unregistered_views)}


def components(view_ids: list[int], edges: list[tuple[int, int]]) -> dict[int, int]:
    """Connected-component label of every view id (scipy union-find, no per-edge Python)."""
    # scipy lazily: its import (~0.3 s) is not needed by commands that only load this module
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    index = {v: k for k, v in enumerate(view_ids)}
    if edges:
        rows = np.array([index[i] for i, _ in edges])
        cols = np.array([index[j] for _, j in edges])
    else:
        rows = cols = np.zeros(0, dtype=np.int64)
    graph = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(len(view_ids), len(view_ids)))
    _, label = connected_components(graph, directed=False)
    return {v: int(label[k]) for v, k in index.items()}


def largest_component_of(view_ids: list[int], edges: list[tuple[int, int]]) -> list[int]:
    """Sorted view ids of the largest connected component of ``edges`` (views of
    ``view_ids`` without an edge do not count); ties: the component holding the smallest
    view id; [] without edges."""
    label = components(view_ids, edges)
    touched = {v for edge in edges for v in edge}
    sizes: dict[int, int] = {}
    for v in touched:
        sizes[label[v]] = sizes.get(label[v], 0) + 1
    if not sizes:
        return []
    best = min(sizes, key=lambda c: (-sizes[c], min(v for v in touched if label[v] == c)))
    return sorted(v for v in touched if label[v] == best)


def largest_component(graph: ViewGraph, reason: str = "outside largest component") -> list[int]:
    """Keep the largest connected component of the active edges.

    Active edges outside it are filtered with ``reason``; ``graph.unregistered_views`` is set
    to the views outside it. Ties: the component holding the smallest view id. Returns the
    sorted view ids of the component.
    """
    view_ids = graph.view_ids()
    active = graph.active_edges()
    keep = largest_component_of(view_ids, [(graph.edges[k].i, graph.edges[k].j) for k in active])
    kept = set(keep)
    for k in active:
        if graph.edges[k].i not in kept:
            graph.edges[k].filter(reason)
    graph.unregistered_views = [v for v in view_ids if v not in kept]
    return keep


def active_bridges(graph: ViewGraph, views: set[int] | None = None) -> list[int]:
    """The active edges (indices) between ``views`` (default: every view) that no cycle of
    those edges runs through (:func:`bridge_edges`)."""
    edges = [k for k in graph.active_edges()
             if views is None or (graph.edges[k].i in views and graph.edges[k].j in views)]
    bridge = bridge_edges([(graph.edges[k].i, graph.edges[k].j) for k in edges])
    return [k for k, is_bridge in zip(edges, bridge) if is_bridge]


def bridge_edges(edges: list[tuple[int, int]]) -> list[bool]:
    """Per edge (view id pairs), whether it is a bridge: no cycle of ``edges`` runs through it,
    so nothing but its own two-view estimate says where its far side is (cycle consistency
    and the averaging's residuals cannot check it). Iterative DFS with low-links (Tarjan),
    O(views + edges); a repeated pair is a cycle of two."""
    neighbours: dict[int, list[tuple[int, int]]] = {}
    for k, (i, j) in enumerate(edges):
        neighbours.setdefault(i, []).append((j, k))
        neighbours.setdefault(j, []).append((i, k))
    order: dict[int, int] = {}
    low: dict[int, int] = {}
    bridge = [False] * len(edges)
    for root in neighbours:
        if root in order:
            continue
        order[root] = low[root] = len(order)
        stack = [(root, -1, iter(neighbours[root]))]  # (view, edge it was reached by, its neighbours)
        while stack:
            view, via, rest = stack[-1]
            step = next(rest, None)
            if step is None:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[view])
                    if low[view] > order[parent]:
                        bridge[via] = True
                continue
            other, k = step
            if k == via:
                continue
            if other in order:
                low[view] = min(low[view], order[other])
            else:
                order[other] = low[other] = len(order)
                stack.append((other, k, iter(neighbours[other])))
    return bridge


def regular_edges(graph: ViewGraph) -> list[int]:
    """Active REGULAR edges: the ones whose matches constrain a translation."""
    return [k for k in graph.active_edges() if graph.edges[k].scene_kind == SceneKind.REGULAR.value]


def filter_rotation_singular(graph: ViewGraph) -> int:
    """Filter ROTATION_SINGULAR edges and re-check the largest component; returns the count."""
    count = 0
    for k in graph.active_edges():
        if graph.edges[k].scene_kind == SceneKind.ROTATION_SINGULAR.value:
            graph.edges[k].filter(SINGULAR_REASON)
            count += 1
    largest_component(graph)
    return count


def kind_counts(graph: ViewGraph, edges: list[int]) -> dict:
    """Number of ``edges`` of each scene kind."""
    counts = {kind.value: 0 for kind in SceneKind}
    for k in edges:
        counts[graph.edges[k].scene_kind] = counts.get(graph.edges[k].scene_kind, 0) + 1
    return counts


def kinds_text(counts: dict) -> str:
    """``kind_counts`` for a log line: the kinds present, e.g. "REGULAR 27, PURE_ROTATION 1"."""
    return ", ".join(f"{kind} {n}" for kind, n in counts.items() if n) or "none"


def view_index(graph: ViewGraph) -> dict[int, int]:
    """view id -> row of the (n, ...) rotation / centre arrays (sorted view ids)."""
    return {v: k for k, v in enumerate(graph.view_ids())}


def edge_batch(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int]) -> pg.EdgeBatch:
    """EdgeBatch (z = 1 normalized coordinates) of the matches of ``edges``, in that order."""
    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    return _gathered(normalized, ((graph.edges[k].i, graph.edges[k].j, graph.edges[k].matches) for k in edges), counts)


def _gathered(normalized: dict[int, np.ndarray], edges, counts: np.ndarray) -> pg.EdgeBatch:
    """The EdgeBatch of ``edges``, (view i, view j, matches (m, 2)) each, ``counts`` their
    matches: one gather for this process's batches (:func:`edge_batch`) and a cluster
    worker's (:func:`batch_of_arrays`), so both hold the same bits."""
    if not len(counts):
        return pg.EdgeBatch(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(1, dtype=np.int64))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    # filled edge by edge: no list of per-edge copies beside the result (memory at scale)
    x_i = x_j = None
    for (i, j, matches), m0, m1 in zip(edges, offsets[:-1], offsets[1:]):
        if x_i is None:
            first = normalized[int(i)]
            x_i = np.empty((int(offsets[-1]), first.shape[1]), dtype=first.dtype)
            x_j = np.empty_like(x_i)
        np.take(normalized[int(i)], matches[:, 0], axis=0, out=x_i[m0:m1])
        np.take(normalized[int(j)], matches[:, 1], axis=0, out=x_j[m0:m1])
    return pg.pack_flat(x_i, x_j, offsets)


def edge_arrays(graph: ViewGraph, edges: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plain arrays a cluster task gets for ``edges`` (runtime/cluster.py): their views
    (E, 2), match counts (E,) and matches (M, 2) concatenated (int32 where they fit)."""
    views = np.array([(graph.edges[k].i, graph.edges[k].j) for k in edges], dtype=np.int64).reshape(-1, 2)
    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    matches = [graph.edges[k].matches for k in edges]
    largest = max((int(m.max()) for m in matches if m.size), default=0)
    dtype = np.int32 if largest < 2 ** 31 else np.int64
    return views, counts, (np.concatenate(matches).astype(dtype, copy=False) if matches
                           else np.zeros((0, 2), dtype=dtype))


def batch_of_arrays(normalized: dict[int, np.ndarray], arrays: tuple, e0: int, e1: int) -> pg.EdgeBatch:
    """:func:`edge_batch` of edges [e0, e1) of :func:`edge_arrays`' ``arrays`` (on a worker)."""
    views, counts, matches = arrays
    start = int(counts[:e0].sum())
    bounds = start + np.concatenate([[0], np.cumsum(counts[e0:e1])])
    return _gathered(normalized, ((views[k, 0], views[k, 1], matches[bounds[n]:bounds[n + 1]])
                                  for n, k in enumerate(range(e0, e1))), counts[e0:e1])


def edge_residuals_deg(edges: list[Edge], R_cam_from_world: dict[int, np.ndarray]) -> np.ndarray:
    """Angle (deg) between each of ``edges``' relative rotation R_j_from_i and the one
    ``R_cam_from_world`` implies, R_j R_iᵀ (view id -> rotation; every edge's views in it),
    in one batch: the residual of the averaging's view-graph check."""
    from rotonly_cli.geometry import so3

    if not edges:
        return np.zeros(0)
    R_i = np.stack([R_cam_from_world[edge.i] for edge in edges])
    R_j = np.stack([R_cam_from_world[edge.j] for edge in edges])
    R_pair = np.stack([edge.R_j_from_i for edge in edges])
    return np.degrees(so3.geodesic_angle(R_pair, R_j @ np.swapaxes(R_i, 1, 2)))
