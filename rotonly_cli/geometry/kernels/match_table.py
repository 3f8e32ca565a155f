"""The per-match constants of an EdgeBatch in one (13, M) array, for the lean TRRM evaluator
(kernels/lean.py) and the moment kernels (kernels/moments.py): subsets are one gather and
edge groups are views."""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.kernels.soa import edge_groups
from rotonly_cli.geometry.tracks import segment_indices

XI, XJ, XJH, INV_NXI, NXI2, NXJ2, INV_NXJ = 0, 3, 6, 9, 10, 11, 12
TABLE_ROWS = 13
#: matches per edge group of the lean evaluator (8k-32k are within 5 % of each other)
LEAN_CHUNK = 1 << 14


class MatchTable:
    """Per-match constants of an EdgeBatch (rows XI.. above), optional per-match weights,
    and ``match_pos``: the position of each match in the table it was cut from."""

    def __init__(self, data: np.ndarray, offsets: np.ndarray, weights: np.ndarray | None,
                 match_pos: np.ndarray | None = None, chunk: int = LEAN_CHUNK):
        self.data = data
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.weights = weights
        self.match_pos = np.arange(data.shape[1]) if match_pos is None else match_pos
        self.counts = np.diff(self.offsets)
        self.chunk = chunk
        self.groups = edge_groups(self.counts, chunk) if len(self.counts) else []
        self._group_slices: list | None = None

    @classmethod
    def from_batch(cls, batch: pg.EdgeBatch, weights: np.ndarray | None = None,
                   chunk: int = LEAN_CHUNK) -> MatchTable:
        M = batch.x_i.shape[0]
        data = np.empty((TABLE_ROWS, M))
        data[XI:XI + 3] = batch.x_i.T
        data[XJ:XJ + 3] = batch.x_j.T
        xi, xj = data[XI:XI + 3], data[XJ:XJ + 3]
        np.einsum("km,km->m", xi, xi, out=data[NXI2])
        np.einsum("km,km->m", xj, xj, out=data[NXJ2])
        data[INV_NXI] = 1.0 / np.sqrt(data[NXI2])
        data[INV_NXJ] = 1.0 / np.sqrt(data[NXJ2])
        data[XJH:XJH + 3] = xj * data[INV_NXJ]
        w = batch.weights if weights is None else weights
        return cls(data, batch.offsets, None if w is None else np.ascontiguousarray(w, dtype=float), chunk=chunk)

    @property
    def num_edges(self) -> int:
        return len(self.counts)

    def group_slices(self) -> list[tuple[int, int, int, int, np.ndarray, np.ndarray]]:
        """Per edge group: (e0, e1, m0, m1, counts, starts within the group), computed once."""
        if self._group_slices is None:
            self._group_slices = [(e0, e1, int(self.offsets[e0]), int(self.offsets[e1]), self.counts[e0:e1],
                                   self.offsets[e0:e1] - self.offsets[e0]) for e0, e1 in self.groups]
        return self._group_slices

    def group_code_range(self, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest of a per-edge integer ``code`` within each group."""
        if not self.groups:
            return np.zeros(0, dtype=code.dtype), np.zeros(0, dtype=code.dtype)
        first = np.array([e0 for e0, _ in self.groups])
        return np.minimum.reduceat(code, first), np.maximum.reduceat(code, first)

    def match_index(self, edges: np.ndarray) -> np.ndarray:
        """Positions (in this table) of the matches of ``edges``, edge by edge."""
        return segment_indices(self.offsets[:-1][edges], self.counts[edges])

    def subset(self, edges: np.ndarray) -> MatchTable:
        edges = np.asarray(edges, dtype=np.int64)
        idx = self.match_index(edges)
        offsets = np.concatenate([[0], np.cumsum(self.counts[edges])])
        return MatchTable(self.data[:, idx], offsets, None if self.weights is None else self.weights[idx],
                          self.match_pos[idx], self.chunk)

    def with_weights(self, weights: np.ndarray | None) -> MatchTable:
        return MatchTable(self.data, self.offsets, weights, self.match_pos, self.chunk)
