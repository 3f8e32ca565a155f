"""The fixed structure of a GRRM problem, laid out so that memory grows with the matches and
not with the square of the track length (issue 49).

A *contribution* is one side of one match: side i of match m is the observation (view i,
its keypoint), side j the observation (view j, its keypoint). An observation's residual V_g
(eq:GRRMRes2) is the ω-weighted mean of its contributions' residuals, so its Jacobian J_g is
a sum over the contributions, and J_gᵀJ_g holds a block for every *pair* of contributions of
the observation: Σ_g k_g² blocks for k_g contributions, the cube of the track length per track.
Those pairs are never stored: each block of contributions generates its pairs when it is
accumulated, and the pair's place in the normal equations is arithmetic. The two edges of a
pair both hold the observation's view v, so the block (e_a, e_b) is addressed as
``base[v] + pos_a * deg[v] + pos_b`` (pos: the edge's place among the edges at v), a dense
deg[v] x deg[v] table per view; no sort and no lookup per pair.

Per-match terms are computed per *part*: a range of views (in reverse Cuthill-McKee order of
the view graph, so that a part's edges mostly stay inside it) whose observations' contributions
come from the matches of the edges at those views. A part fills a table of those edges'
match terms, evaluates its observations, and drops the table; an edge between two parts is
computed in both (a few per cent of the edges). The persistent state is two int32 per
contribution (its row in the part's table and its edge) and the per-observation sizes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from rotonly_cli.geometry.tracks import EVALUATION_PARTS, even_ranges, segment_indices

#: contributions per block (blocks of ~1 MB arrays stay in cache; block edges fall on
#: observation boundaries, and an observation's pairs stay inside its block)
CHUNK = 1 << 15
#: incident matches per part: a part's table of match terms (16 float64 per side) and its
#: matches' copy stay near 200 MB
PART_MATCHES = 1 << 19
#: above this many dense pair blocks (Σ deg[v]², 9 float64 each) the pair blocks are
#: addressed through a sorted table of the blocks that occur instead (a view matched to
#: thousands of others)
DENSE_PAIR_BLOCKS = 1 << 22


@dataclass
class Part:
    """The observations of a range of views and the edges their contributions come from."""

    edges: np.ndarray  #: (Ep,) global edges at the part's views, ascending
    num_matches: int  #: matches of those edges (rows of side i in the part's table; side j: + this)
    rows: np.ndarray  #: (Cp,) int32: each contribution's row in the part's table
    edge: np.ndarray  #: (Cp,) int32: each contribution's global edge
    sizes: np.ndarray  #: (Gp,) contributions per observation
    g0: int  #: the part's first observation in GRRM's observation order
    blocks: list  #: (s0, s1, g0, g1) contribution and observation ranges, local to the part

    @property
    def num_contributions(self) -> int:
        return len(self.rows)


def view_order(n: int, edge_views: np.ndarray) -> np.ndarray:
    """rank[v]: the place of view v in the reverse Cuthill-McKee order of the view graph
    (neighbours near each other, so a range of views holds most of its edges)."""
    if n == 0 or not len(edge_views):
        return np.arange(n)
    ones = np.ones(len(edge_views), dtype=np.int8)
    A = sp.csr_matrix((ones, (edge_views[:, 0], edge_views[:, 1])), shape=(n, n))
    perm = reverse_cuthill_mckee((A + A.T).tocsr(), symmetric_mode=True)
    rank = np.empty(n, dtype=np.int64)
    rank[perm] = np.arange(n)
    return rank


class Layout:
    """Observations, parts and the pair-block addressing of one GRRM problem.

    Observation order: by view (rank order), then by id; within an observation its
    contributions in match order, side i before side j of the same match's id group
    (a stable sort of (rank of view, id)). ``id_order`` maps it to the observations sorted by
    id alone (the order of :func:`grrm_residuals`'s output)."""

    def __init__(self, n: int, edge_views: np.ndarray, offsets: np.ndarray, obs_ids: np.ndarray,
                 part_matches: int | None = None, chunk: int | None = None):
        part_matches = PART_MATCHES if part_matches is None else part_matches
        chunk = CHUNK if chunk is None else chunk
        E = len(edge_views)
        counts = np.diff(offsets)
        M = int(offsets[-1])
        self.n, self.E, self.M = n, E, M
        self.edge_views = edge_views
        rank = view_order(n, edge_views)
        # --- parts: view ranges in rank order with about equal incident matches
        incident = np.bincount(edge_views[:, 0], counts, minlength=n) + np.bincount(edge_views[:, 1], counts,
                                                                                     minlength=n)
        perm = np.argsort(rank)
        num_parts = max(EVALUATION_PARTS, -(-int(incident.sum()) // max(part_matches, 1)))
        # --- each part's contributions sorted by (rank of their view, observation id), one part
        # at a time: a part's keys form their own range, so its stable sort is the global one's
        # restriction (no sort and key of all 2M contributions at once: 40 B per match)
        span = int(obs_ids.max()) + 1 if M else 1
        self.parts: list[Part] = []
        part_ids = []  # per part: its observations' ids, in observation order
        g0 = 0
        for r0, r1 in even_ranges(incident[perm], num_parts):
            in_part = np.zeros(n, dtype=bool)
            in_part[perm[r0:r1]] = True
            at = in_part[edge_views]  # (E, 2): the edge's side-i / side-j view is in the part
            edges = np.flatnonzero(at[:, 0] | at[:, 1])
            index, key = [], []  # the part's contributions (side * M + match, ascending) and their keys
            for side in range(2):
                e_s = np.flatnonzero(at[:, side])
                match = segment_indices(offsets[e_s], counts[e_s])
                index.append(match + side * M)
                key.append(np.repeat(rank[edge_views[e_s, side]] * span, counts[e_s]) + obs_ids[match, side])
            index, key = np.concatenate(index), np.concatenate(key)
            order = np.argsort(key, kind="stable")
            key = key[order]
            first = np.ones(len(key), dtype=bool)
            first[1:] = key[1:] != key[:-1]
            starts = np.flatnonzero(first)
            part_ids.append(key[starts] % span)
            self.parts.append(self._part(edges, offsets, index[order], np.diff(np.append(starts, len(key))), g0,
                                         chunk))
            g0 += len(starts)
        self.num_groups = g0
        # the observations in id order (ties: rank order), for outputs indexed like the ids
        self.id_order = np.argsort(np.concatenate(part_ids), kind="stable")  # id_order[k]: observation of the k-th id
        # --- pair blocks: the edges at each view, and each edge's place there
        self.deg = np.bincount(edge_views.ravel(), minlength=n)
        at_view = np.argsort(edge_views.ravel(), kind="stable")  # (2E,) edge-side slots, grouped by view
        view_start = np.concatenate([[0], np.cumsum(self.deg)])
        self.inc_pos = np.empty(2 * E, dtype=np.int64)  # [2e + side]: place of edge e among its view's edges
        self.inc_pos[at_view] = np.arange(2 * E) - np.repeat(view_start[:-1], self.deg)
        self._inc_edge = at_view // 2
        self._view_start = view_start
        self.base = np.concatenate([[0], np.cumsum(self.deg * self.deg)])
        self._occurring = None
        if int(self.base[-1]) > DENSE_PAIR_BLOCKS:
            self._occurring = self._occurring_blocks()
        blocks = np.arange(int(self.base[-1])) if self._occurring is None else self._occurring
        self.block_row, self.block_col = self._block_edges(blocks)
        self.num_blocks = len(blocks)

    @property
    def dense_pair_blocks(self) -> bool:
        """Pair blocks addressed in dense per-view tables (base[v] + a deg[v] + b)."""
        return self._occurring is None

    def edges_at(self, v: int) -> np.ndarray:
        """The edges at view v, in their places (inc_pos) there."""
        return self._inc_edge[self._view_start[v]:self._view_start[v + 1]]

    def _block_edges(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The edges (row, column) of dense pair blocks ``index``: block base[v] + a deg[v] + b
        pairs the edges at places a and b of view v."""
        v = np.searchsorted(self.base, index, side="right") - 1
        local = index - self.base[v]
        d = np.maximum(self.deg[v], 1)
        start = self._view_start[v]
        return self._inc_edge[start + local // d], self._inc_edge[start + local % d]

    def _part(self, edges, offsets, order_slice, sizes, g0, chunk) -> Part:
        M = self.M
        counts = np.diff(offsets)
        local_offsets = np.concatenate([[0], np.cumsum(counts[edges])])
        Mp = int(local_offsets[-1])
        side = order_slice >= M
        match = np.where(side, order_slice - M, order_slice)
        edge = np.searchsorted(offsets, match, side="right") - 1
        local_edge = np.searchsorted(edges, edge)
        rows = local_offsets[local_edge] + (match - offsets[edge]) + side * Mp
        cuts = np.concatenate([[0], np.cumsum(sizes)])
        # blocks of about ``chunk`` contributions, cut at observation starts
        g_cuts = np.unique(np.searchsorted(cuts, np.arange(0, cuts[-1], chunk), side="right") - 1)
        g_bounds = np.concatenate([g_cuts, [len(sizes)]]) if len(sizes) else np.zeros(1, dtype=np.int64)
        blocks = [(int(cuts[a]), int(cuts[b]), int(a), int(b)) for a, b in zip(g_bounds[:-1], g_bounds[1:])]
        return Part(edges=edges, num_matches=Mp, rows=rows.astype(np.int32 if 2 * Mp < 2**31 else np.int64),
                    edge=edge.astype(np.int32), sizes=sizes.astype(np.int64), g0=g0, blocks=blocks)

    def pair_blocks(self, edge: np.ndarray, side: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
        """The normal-equation block of each pair (pa[k], pb[k]) of contributions of one
        observation, from the contributions' edges and sides (0: the view is the edge's i)."""
        slot = 2 * edge.astype(np.int64) + side
        v = self.edge_views[edge[pa], side[pa]]
        index = self.base[v] + self.inc_pos[slot[pa]] * self.deg[v] + self.inc_pos[slot[pb]]
        if self._occurring is not None:
            index = np.searchsorted(self._occurring, index)
        return index

    def _occurring_blocks(self) -> np.ndarray:
        """The dense indices of the pair blocks that occur (one pass over every pair)."""
        seen = [np.zeros(0, dtype=np.int64)]
        for part in self.parts:
            side = (part.rows >= part.num_matches).astype(np.int64)
            for s0, s1, g0, g1 in part.blocks:
                pa, pb = pairs_in_block(part.sizes[g0:g1])
                if len(pa):
                    seen.append(np.unique(self.pair_blocks(part.edge[s0:s1], side[s0:s1], pa, pb)))
        return np.unique(np.concatenate(seen))


def pairs_in_block(sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (a < b) of every pair of contributions inside each observation of a block
    (observations of ``sizes`` contributions, contiguous), ordered by observation, a, b."""
    from rotonly_cli.geometry.tracks import pairs_within_tracks

    return pairs_within_tracks(np.concatenate([[0], np.cumsum(sizes)]))
