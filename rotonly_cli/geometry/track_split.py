"""Tracks that a wrong match merged, cut into their consistent parts under known poses.

Pure numpy/scipy. A component of the match graph that sees one view twice
(geometry.tracks.ConflictGraph) is not one point: a wrong match hung a second keypoint of a
view on a track (a match moved along its epipolar line passes every two-view test), or
joined two tracks. Dropping such components whole loses almost every long track once a few
per cent of the matches are wrong (issue 49: 1000 views, 5 % wrong matches, 10 567 of
100 000 points). Instead, as COLMAP's triangulator does with RANSAC over a track's
observations, each component is fitted robustly, all components at once:

1. hypotheses: per component ``HYPOTHESES`` midpoints of the rays of two of its nodes drawn
   at random (the wrong keypoints are a small minority of a component's nodes);
2. the hypothesis that reprojects within ``INLIER_FACTOR`` x the threshold at the most nodes
   is refined (linear + Gauss-Newton) on those nodes, then ``REFINEMENTS`` times on the
   members: the nodes within the threshold, at most one per view (the one that fits best);
3. the members are a part (they reproject onto one point, one node per view); every match
   between a member and the rest is cut.

The rest (a merged second track, a wrong keypoint), with the matches among them, forms new
components: one that sees every view once is a part (tested, like every track, by the
triangulate stage), one that still sees a view twice is split again, for up to
``MAX_ROUNDS``. A component no hypothesis holds two nodes of is dropped, as are nodes left
alone. A round is a few passes over the nodes (``HYPOTHESES`` projections, bincounts, two
batched triangulations) and one over the matches; no loop over components.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry.tracks import ConflictGraph
from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks

__all__ = ["SplitResult", "split_conflicts"]

#: two-ray points tried per component and round: with a fraction w of wrong nodes in a
#: component, a pair holds one with probability 1 - (1 - w)^2, all eight pairs do with
#: (1 - (1 - w)^2)^8 (w = 0.2: 3e-4; the simulated 5 % wrong matches leave w < 0.1: 2e-6)
HYPOTHESES = 8
#: rounds of fit -> cut -> re-component; each takes the members (two nodes or more) out of
#: every component it fits and drops the others (measured inputs settle in one or two)
MAX_ROUNDS = 4
#: a hypothesis from two rays is scored with this factor on the threshold: its depth is only
#: as good as its baseline, the refined point is held to the threshold itself
INLIER_FACTOR = 2.0
#: refinements of the best hypothesis on its members (each: linear + Gauss-Newton, new members)
REFINEMENTS = 2
_LOOSE = TriangulationOptions(max_reprojection_error=np.inf, min_parallax_deg=0.0, num_refinement_iterations=3)


@dataclass
class SplitResult:
    """Per conflict node its part (0..num_parts-1) or -1 (dropped); the counts the report gives."""

    part: np.ndarray  # (N_nodes,) int64
    num_parts: int
    num_components: int  # the conflicting components given
    num_rounds: int
    num_matches_cut: int
    num_nodes_unsettled: int  # in components still seeing a view twice after MAX_ROUNDS (dropped)
    num_components_lost: int  # components none of whose nodes is in a part

    def report(self) -> dict:
        return {"num_conflicting_components": self.num_components, "num_parts": self.num_parts,
                "num_matches_cut": self.num_matches_cut, "num_components_lost": self.num_components_lost,
                "num_nodes_unsettled": self.num_nodes_unsettled, "rounds": self.num_rounds}


def _components(num_nodes: int, edges: np.ndarray) -> np.ndarray:
    """Component label (0..k-1) per node of the graph ``edges`` (node indices < num_nodes)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(num_nodes, num_nodes))
    return connected_components(graph, directed=False)[1]


def _sees_a_view_twice(label: np.ndarray, view: np.ndarray, num_labels: int) -> np.ndarray:
    """Per label: two of its nodes share a view."""
    order = np.lexsort((view, label))
    same = (label[order][1:] == label[order][:-1]) & (view[order][1:] == view[order][:-1])
    twice = np.zeros(num_labels, dtype=bool)
    twice[label[order][1:][same]] = True
    return twice


class _Nodes:
    """The poses and rays of a round's nodes, gathered once: each hypothesis is scored on all."""

    def __init__(self, R: np.ndarray, C: np.ndarray, view: np.ndarray, xy: np.ndarray):
        self.R, self.C, self.xy = R[view], C[view], xy  # (N, 3, 3), (N, 3), (N, 2)
        rays = np.einsum("nji,nj->ni", self.R, np.c_[xy, np.ones(len(xy))])  # R^T (x, y, 1)
        self.rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def errors(self, X: np.ndarray) -> np.ndarray:
        """Normalized reprojection error of every node against its point X (N, 3); inf behind
        the camera or where X is not finite."""
        camera = np.einsum("nij,nj->ni", self.R, X - self.C)
        with np.errstate(all="ignore"):
            error = np.linalg.norm(camera[:, :2] / camera[:, 2:3] - self.xy, axis=1)
        return np.where((camera[:, 2] > 0) & np.isfinite(error), error, np.inf)

    def midpoints(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The midpoint of the closest approach of the rays of nodes a and b (K, 3); NaN where
        they are parallel or meet behind either camera."""
        da, db, w = self.rays[a], self.rays[b], self.C[a] - self.C[b]
        cosine = np.einsum("ki,ki->k", da, db)
        pa, pb = np.einsum("ki,ki->k", da, w), np.einsum("ki,ki->k", db, w)
        with np.errstate(all="ignore"):
            denominator = 1.0 - cosine ** 2
            s = (cosine * pb - pa) / denominator  # depth along ray a
            t = (pb - cosine * pa) / denominator  # along ray b
            X = 0.5 * (self.C[a] + s[:, None] * da + self.C[b] + t[:, None] * db)
        return np.where(((denominator > 1e-12) & (s > 0) & (t > 0))[:, None], X, np.nan)


def _best_of_view(label: np.ndarray, view: np.ndarray):
    """A function ``(error, fits) -> fits`` with, per (label, view), only the node of smallest
    error: the nodes that share a view with another of their label are found once, and only
    they are sorted by error."""
    _, group, count = np.unique(label * (int(view.max()) + 1) + view, return_inverse=True, return_counts=True)
    shared = np.flatnonzero(count[group] > 1)

    def best(error: np.ndarray, fits: np.ndarray) -> np.ndarray:
        order = shared[np.lexsort((error[shared], group[shared]))]
        later = np.r_[False, group[order][1:] == group[order][:-1]]
        fits = fits.copy()
        fits[order[later]] = False
        return fits

    return best


def _points_of(R, C, label, view, xy, use, num_labels) -> tuple[np.ndarray, np.ndarray]:
    """(points (num_labels, 3), NaN where fewer than two ``use`` nodes; per label: solved)
    triangulated from the ``use`` nodes; ``label`` must be non-decreasing."""
    counts = np.bincount(label[use], minlength=num_labels)
    use = use & (counts[label] >= 2)
    points = np.full((num_labels, 3), np.nan)
    if use.any():
        solved = triangulate_tracks(R, C, label[use], view[use], xy[use], num_labels, _LOOSE, with_parallax=False)
        points = solved.points_in_world
    return points, np.all(np.isfinite(points), axis=1)


def _fit_round(R, C, label, view, xy, threshold, num_labels, rng) -> tuple[np.ndarray, np.ndarray]:
    """(members, fitted per label) of one round; nodes sorted by ``label``."""
    nodes = _Nodes(R, C, view, xy)
    # hypotheses: per label the rays of two of its nodes at random (two of one view: none)
    size = np.bincount(label, minlength=num_labels)
    start = np.concatenate([[0], np.cumsum(size)[:-1]])
    best_score = np.full(num_labels, -1)
    best_point = np.full((num_labels, 3), np.nan)
    for _ in range(HYPOTHESES):
        a, b = (start + (rng.random((2, num_labels)) * size).astype(np.int64))
        point = nodes.midpoints(a, b)
        inlier = nodes.errors(point[label]) <= INLIER_FACTOR * threshold
        score = np.bincount(label[inlier], minlength=num_labels)
        better = score > best_score
        best_score = np.where(better, score, best_score)
        best_point[better] = point[better]
    members = nodes.errors(best_point[label]) <= INLIER_FACTOR * threshold
    fitted = best_score >= 2
    best_of_view = _best_of_view(label, view)
    for _ in range(REFINEMENTS):
        point, solved = _points_of(R, C, label, view, xy, members, num_labels)
        fitted &= solved
        error = nodes.errors(point[label])
        members = best_of_view(error, error <= threshold)
    fitted &= np.bincount(label[members], minlength=num_labels) >= 2
    return members & fitted[label], fitted


def _dense(label: np.ndarray, num_labels: int) -> tuple[np.ndarray, int]:
    """(``label`` renumbered 0..k-1 in order, k)."""
    present = np.bincount(label, minlength=num_labels) > 0
    new = np.cumsum(present) - 1
    return new[label], int(present.sum())


def split_conflicts(R_cam_from_world: np.ndarray, centers: np.ndarray, conflicts: ConflictGraph,
                    xy: np.ndarray, threshold: np.ndarray, seed: int = 0) -> SplitResult:
    """Cut the components of ``conflicts`` into parts that see every view at most once and
    reproject within ``threshold`` (module docstring).

    Args:
        R_cam_from_world, centers: (n, 3, 3), (n, 3) the poses of the views (finite for
            every view a node lies in).
        conflicts: the components (geometry.tracks.build_tracks with ``keep_conflicts``).
        xy: (N_nodes, 2) normalized image coordinates of the nodes.
        threshold: (N_nodes,) the largest normalized reprojection error of a member, per node.
        seed: of the random choice of hypotheses.
    """
    R = np.asarray(R_cam_from_world, dtype=float)
    C = np.asarray(centers, dtype=float)
    view = np.asarray(conflicts.view, dtype=np.int64)
    xy = np.asarray(xy, dtype=float)
    threshold = np.asarray(threshold, dtype=float)
    num_nodes = view.size
    edges = np.asarray(conflicts.edges).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    part = np.full(num_nodes, -1, dtype=np.int64)
    active, label = np.arange(num_nodes), np.asarray(conflicts.component, dtype=np.int64)
    num_parts = num_cut = rounds = 0
    while active.size and rounds < MAX_ROUNDS:
        rounds += 1
        order = np.argsort(label, kind="stable")
        active, label = active[order], label[order]
        members, fitted = _fit_round(R, C, label, view[active], xy[active], threshold[active],
                                     int(label.max()) + 1, rng)
        # the members of each fitted component are a part
        new, count = _dense(label[members], int(label.max()) + 1)
        part[active[members]] = num_parts + new
        num_parts += count
        # the matches between members and the rest are cut; a component no hypothesis fits
        # is dropped; the rest, with the matches among them, is split again
        member = np.zeros(num_nodes, dtype=bool)
        member[active[members]] = True
        was_active = np.zeros(num_nodes, dtype=bool)
        was_active[active] = True
        num_cut += int(np.sum(was_active[edges[:, 0]] & (member[edges[:, 0]] != member[edges[:, 1]])))
        rest = active[~members & fitted[label]]
        local = np.full(num_nodes, -1, dtype=np.int64)
        local[rest] = np.arange(rest.size)
        edges = edges[(local[edges[:, 0]] >= 0) & (local[edges[:, 1]] >= 0)]
        component = _components(rest.size, local[edges])
        num_components = int(component.max()) + 1 if rest.size else 0
        twice = _sees_a_view_twice(component, view[rest], num_components)
        size = np.bincount(component, minlength=num_components)
        settled = ~twice[component] & (size[component] >= 2)
        # a consistent component of the rest is a part (its observations are tested like any track's)
        new, count = _dense(component[settled], num_components)
        part[rest[settled]] = num_parts + new
        num_parts += count
        active, label = rest[twice[component]], _dense(component[twice[component]], num_components)[0]
    return SplitResult(part, num_parts, conflicts.num_components, rounds, num_cut, int(active.size),
                       _components_lost(conflicts.component, part))


def _components_lost(component: np.ndarray, part: np.ndarray) -> int:
    """Components none of whose nodes ended in a part."""
    if not component.size:
        return 0
    kept = np.zeros(int(component.max()) + 1, dtype=bool)
    kept[component[part >= 0]] = True
    return int((~kept).sum())
