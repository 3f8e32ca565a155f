"""The fixed structure of a GRRM problem and its evaluation: per-observation residuals V_ik
(eq:GRRMRes2), their exact Jacobian blocks, and the normal equations accumulated block by
block without forming J."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import scipy.sparse as sp

from rotonly_cli.geometry import kernels
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.robust import radial_excess, robust_curvature, robust_rho
from rotonly_cli.geometry.tracks import EVALUATION_PARTS, even_ranges

#: contributions per block in GRRMSystem (blocks of ~1 MB arrays stay in cache, and no
#: per-iteration temporary grows with the problem: arrays above glibc's 32 MB mmap
#: threshold would be page-faulted afresh on every allocation)
_CHUNK = 1 << 15
#: up to this many views the 3n x 3n normal equations are assembled and solved dense (same
#: mathematics; at n ~ 10 scipy's sparse assembly and SuperLU cost more than the numbers)
_DENSE_MAX_VIEWS = 200


def _to_image_plane(side: np.ndarray, x, with_jacobian: bool) -> None:
    """In place: bearing residual x̂ - ŝ (rows 0-2, derivatives rows 7-15) -> image-plane
    residual x/x_z - ŝ/ŝ_z of eq:PA3 / eq:GRRMRes1 (third component 0); contributions whose
    reprojection is not in front of the camera get ω numerator 0."""
    inv_norm = 1.0 / np.sqrt(kernels.dot(x, x))
    s_hat = [x[a] * inv_norm - side[a] for a in range(3)]
    valid = (s_hat[2] > 1e-12) & (x[2] > 0)
    inv_sz = np.where(valid, 1.0 / np.where(valid, s_hat[2], 1.0), 0.0)
    inv_xz = np.where(valid, 1.0 / np.where(valid, x[2], 1.0), 0.0)
    p = [s_hat[a] * inv_sz for a in range(2)]
    for a in range(2):
        side[a] = x[a] * inv_xz - p[a]
    side[2] = 0.0
    side[3] *= valid
    if with_jacobian:
        # d(ŝ/ŝ_z) = (dŝ - p dŝ_z) / ŝ_z with dŝ = -d(x̂ - ŝ)
        side[4:7] *= valid
        for c in range(3):
            dz = side[13 + c].copy()
            for a in range(2):
                side[7 + 3 * a + c] = (side[7 + 3 * a + c] - p[a] * dz) * inv_sz
            side[13 + c] = 0.0


class GRRMSystem:
    """The fixed structure of a GRRM problem: edges, matches, observation groups, and the
    sparsity pattern of the normal equations (computed once, refilled every iteration).

    Normal equations without a huge J: J = J_e C, where J_e (3G x 3E) holds one 3x3 block
    B_c per contribution (match side c -> its observation g, derivative w.r.t. its edge's
    δ_e) and C (3E x 3n) chains δ_e = δ_j - R_ij δ_i. Then JᵀJ = Cᵀ (J_eᵀ J_e) C with
    J_eᵀ J_e = Σ_g Σ_{c, c' in g} B_cᵀ B_c' at block (e_c, e_c'): the pairs of contributions
    inside each observation are enumerated once; each iteration only refills the blocks.

    Layout (for speed): contributions are held sorted by observation, so per-observation
    sums are segment sums over contiguous runs and the pairs of an observation are
    neighbours; all per-contribution work runs block by block (``_CHUNK`` contributions,
    block edges on observation boundaries), each 3-vector / 3x3 block as 1-D component
    arrays (structure of arrays): a 3x3 product is 27 elementwise multiply-adds.
    """

    def __init__(self, n: int, edge_views: np.ndarray, batch: pg.EdgeBatch, obs_ids: np.ndarray,
                 residual_form: str = "bearing"):
        from rotonly_cli.geometry.tracks import pairs_within_tracks

        self.n = n
        self.image_plane = residual_form == "image"
        self.E = batch.num_edges
        self.edge_views = edge_views
        self._peer = None  # the helper process evaluating the parts after the first (:meth:`parallel`)
        self.processes = 1  # processes the last :meth:`parallel` ran in
        self._peer_batch = None  # the batch the peer has
        self.batch = batch
        self.M = batch.x_i.shape[0]
        edge_of_match = np.repeat(np.arange(batch.num_edges), batch.counts)
        # every match contributes to two observations: (view i, its keypoint) and (view j, ...)
        ids = np.concatenate([obs_ids[:, 0], obs_ids[:, 1]])
        # contributions sorted by observation (contribution c < M: side i of match c, else
        # side j of match c - M); pairs (a < b) inside each observation are positions in that
        # sorted order, ascending in a (tracks.pairs_within_tracks). One stable sort of the ids
        # themselves (timsort: the ids come in sorted runs per edge), then runs of equal ids
        self.order = np.argsort(ids, kind="stable")
        ids_sorted = ids[self.order]
        first = np.ones(len(ids), dtype=bool)
        first[1:] = ids_sorted[1:] != ids_sorted[:-1]
        self.starts = np.flatnonzero(first)
        self.sizes = np.diff(np.append(self.starts, len(ids)))
        self.num_groups = len(self.sizes)
        self.group_sorted = np.repeat(np.arange(self.num_groups), self.sizes)
        self.edge_sorted = np.concatenate([edge_of_match, edge_of_match])[self.order]
        offsets = np.concatenate([[0], np.cumsum(self.sizes)])
        self.pair_a, self.pair_b = pairs_within_tracks(offsets)
        key = self.edge_sorted[self.pair_a] * self.E + self.edge_sorted[self.pair_b]
        if self.E * self.E <= 1 << 24:  # distinct edge pairs by a table lookup instead of a sort
            present = np.bincount(key, minlength=self.E * self.E) > 0
            self.block_keys = np.flatnonzero(present)
            self.pair_block = (np.cumsum(present) - 1)[key]
        else:
            self.block_keys, self.pair_block = np.unique(key, return_inverse=True)
        self.block_row = self.block_keys // self.E
        self.block_col = self.block_keys % self.E
        # blocks of sorted contributions, cut at observation starts: (s0, s1, g0, g1, p0, p1)
        cuts = np.unique(np.searchsorted(offsets, np.arange(0, 2 * self.M, _CHUNK), side="right") - 1)
        g_bounds = np.concatenate([cuts, [self.num_groups]])
        s_bounds = offsets[g_bounds]
        p_bounds = np.searchsorted(self.pair_a, s_bounds)
        self.blocks = [(int(s_bounds[k]), int(s_bounds[k + 1]), int(g_bounds[k]), int(g_bounds[k + 1]),
                        int(p_bounds[k]), int(p_bounds[k + 1])) for k in range(len(cuts))]
        # the parts (EVALUATION_PARTS; :meth:`parallel`): edge ranges with about equal matches, block ranges with about
        # equal contributions
        self.edge_parts = even_ranges(batch.counts, EVALUATION_PARTS)
        self.block_parts = even_ranges(np.diff(s_bounds), EVALUATION_PARTS)
        self._table: np.ndarray | None = None  # (2M, 16) per-contribution terms, reused
        self._B: np.ndarray | None = None  # (9, 2M) Jacobian blocks, reused

    def relative(self, R: np.ndarray) -> np.ndarray:
        return R[self.edge_views[:, 1]] @ np.swapaxes(R[self.edge_views[:, 0]], 1, 2)

    @contextmanager
    def parallel(self, peer_class=None):
        """Within: the parts after the first are evaluated by a helper process, side by side
        with this one (the same numbers). ``peer_class``: how to start it (the class of
        runtime.parallel.ForkedPeer: ``peer_class(handler)`` a context manager with submit /
        collect, ``peer_class.shared_array(shape)`` memory both processes write); None, or
        fewer than two parts: one process. The per-match table is then a shared array the
        helper fills its edges' rows of."""
        if peer_class is None or self._peer is not None or len(self.edge_parts) < 2:
            self.processes = 2 if self._peer is not None else 1
            yield self
            return
        self.processes = 2
        self._table = peer_class.shared_array((2 * self.M, 16))
        self._peer_batch = self.batch  # the helper starts with it
        with peer_class(self._serve) as peer:
            self._peer = peer
            try:
                yield self
            finally:
                self._peer = None

    def _serve(self, message):
        """The helper's side of :meth:`parallel`: the table rows of its edges, or the
        sums of its blocks."""
        kind, batch, args = message
        if batch is not None:
            self.batch = batch
        if kind == "table":
            for e0, e1 in self.edge_parts[1:]:
                self._fill_table(*args, e0, e1)
            return None
        return [self._part_sums(*args, part) for part in self.block_parts[1:]]

    def _submit(self, kind: str, *args) -> None:
        batch = None
        if self._peer_batch is not self.batch:
            batch = self._peer_batch = self.batch
        self._peer.submit((kind, batch, args))

    def _match_table(self, R_ij: np.ndarray, with_jacobian: bool) -> np.ndarray:
        """Per-contribution terms in match order, row-major (one 128-byte row per
        contribution, so the gather into observation order is one cache miss each):
        columns 0-2 the residual (in the camera of the observation), 3 the ω numerator,
        4-6 its derivative, 7-15 the residual's derivative (7 + 3a + c = d res_a / dδ_c),
        w.r.t. the left perturbation of the contribution's edge."""
        if self._table is None:
            self._table = np.empty((2 * self.M, 16))
        parts = self.edge_parts
        if self._peer is not None:
            self._submit("table", R_ij, with_jacobian)
            parts = parts[:1]
        for e0, e1 in parts:
            self._fill_table(R_ij, with_jacobian, e0, e1)
        if self._peer is not None:
            self._peer.collect()
        return self._table

    def _fill_table(self, R_ij: np.ndarray, with_jacobian: bool, e_lo: int, e_hi: int) -> None:
        """The rows of :meth:`_match_table` of the matches of edges [e_lo, e_hi)."""
        M = self.M
        table = self._table
        width = 16 if with_jacobian else 4
        for e0, e1, m0, m1, cnt, starts, xi, xj, wk in kernels.edge_chunks(self.batch, kernels.CHUNK_MATCHES,
                                                                           e_lo, e_hi):
            terms = self.chunk_terms(R_ij, e0, e1, cnt, starts, xi, xj, with_jacobian, wk)
            Rm = [np.repeat(R_ij[e0:e1].reshape(-1, 9)[:, k], cnt) for k in range(9)]  # Rm[3b + a] = R_ij[b, a]
            r = terms["r"]  # 6 arrays: r_i in camera-j axes, then r_j
            side_i = np.empty((width, m1 - m0))
            side_j = np.empty((width, m1 - m0))
            for a in range(3):
                # R_ij^T r: view i's residual in camera i
                side_i[a] = Rm[a] * r[0] + Rm[3 + a] * r[1] + Rm[6 + a] * r[2]
                side_j[a] = r[3 + a]
            side_i[3] = side_j[3] = terms["b"] * terms["w"]  # ω numerators (eq:weight); invalid weigh 0
            if with_jacobian:
                # d(R^T v) = R^T (dv + [v]x δ) for R <- exp([δ]x) R
                hat = ((None, -r[2], r[1]), (r[2], None, -r[0]), (-r[1], r[0], None))
                for c in range(3):
                    J = terms["J_cols"][c]  # dr / dδ_c, 6 arrays
                    side_i[4 + c] = side_j[4 + c] = terms["db"][c] * terms["w"]
                    d_in_j = [J[k] if hat[k][c] is None else J[k] + hat[k][c] for k in range(3)]
                    for a in range(3):
                        side_i[7 + 3 * a + c] = Rm[a] * d_in_j[0] + Rm[3 + a] * d_in_j[1] + Rm[6 + a] * d_in_j[2]
                        side_j[7 + 3 * a + c] = J[3 + a]
            if self.image_plane:
                _to_image_plane(side_i, xi, with_jacobian)
                _to_image_plane(side_j, xj, with_jacobian)
            table[m0:m1, :width] = side_i.T
            table[M + m0:M + m1, :width] = side_j.T

    def chunk_terms(self, R_ij: np.ndarray, e0: int, e1: int, cnt: np.ndarray, starts: np.ndarray, xi, xj,
                    with_jacobian: bool, wk: np.ndarray | None) -> dict:
        """The per-match TRRM terms of edges [e0, e1) (kernels.trrm_chunk_terms): the one place
        where each edge's t_ij(R_ij) is made, so a subclass can study other choices."""
        return kernels.trrm_chunk_terms(R_ij[e0:e1], cnt, starts, xi, xj, with_jacobian, wk)

    def _block_terms(self, with_jacobian: bool, blocks: list, B_out: np.ndarray | None = None):
        """Yields, per block of ``blocks`` (of ``self.blocks``), from the table of the last
        :meth:`_match_table`: the block, its observations' residuals V (3, g) and weight sums
        S (g,), and with the Jacobian its contributions' blocks B (9, s) w.r.t. their edge's
        δ_e (row a*3+c = dV_a / dδ_c), written into ``B_out[:, s0:s1]`` if given."""
        width = 16 if with_jacobian else 4
        table = self._table
        for blk in blocks:
            s0, s1, g0, g1, _, _ = blk
            cols = np.ascontiguousarray(table[self.order[s0:s1], :width].T)
            res, b = cols[0:3], cols[3]
            seg = self.starts[g0:g1] - s0
            S_blk = np.add.reduceat(b, seg)
            inv_S = 1.0 / np.where(S_blk > 0, S_blk, 1.0)
            V_blk = np.add.reduceat(b * res, seg, axis=1) * inv_S
            if not with_jacobian:
                yield blk, V_blk, S_blk, None
                continue
            sizes = self.sizes[g0:g1]
            B = np.empty((9, s1 - s0)) if B_out is None else B_out[:, s0:s1]
            inv_S_c = np.repeat(inv_S, sizes)
            b_over_S = b * inv_S_c
            db, dres = cols[4:7], cols[7:16]
            # dV_g = Σ_c [(res_c - V_g) db_c^T + b_c dres_c] / S_g   (ω = b / S, eq:weight)
            for a in range(3):
                dev = (res[a] - np.repeat(V_blk[a], sizes)) * inv_S_c
                for c in range(3):
                    B[3 * a + c] = dev * db[c] + b_over_S * dres[3 * a + c]
            yield blk, V_blk, S_blk, B

    def evaluate(self, R: np.ndarray, with_jacobian: bool):
        """Per-observation residuals V (G, 3), the weight sums S (G,), and optionally the
        per-contribution Jacobian blocks B (9, 2M) w.r.t. their edge's δ_e, in sorted order
        (row a*3+c of B = dV_a / dδ_c). B is a buffer of this problem, valid until the next
        evaluation with the Jacobian."""
        V = np.empty((self.num_groups, 3))
        S = np.empty(self.num_groups)
        if with_jacobian and self._B is None:
            self._B = np.empty((9, 2 * self.M))
        B = self._B if with_jacobian else None
        self._match_table(self.relative(R), with_jacobian)
        for (_, _, g0, g1, _, _), V_blk, S_blk, _ in self._block_terms(with_jacobian, self.blocks, B):
            S[g0:g1] = S_blk
            V[g0:g1] = V_blk.T
        return V, S, B

    def linearize(self, R: np.ndarray, loss: str, scale: float, robust_hessian: bool, with_jacobian: bool,
                  exact_radial_curvature: bool = False):
        """Robust cost Σ ρ(‖V_g‖²) at R and, with the Jacobian, the normal equations
        (JᵀWJ, JᵀWV) of all 3n parameters (W = ρ', with the loss's second-order term clamped
        to β <= 1 if ``robust_hessian``), accumulated block by block (no (9, 2M) Jacobian
        buffer), and with ``exact_radial_curvature`` the remainder Σ ρ'(β - 1)₊ q_gᵀq_g
        (q_g = v̂_gᵀ J_g) that the exact Hessian subtracts (else None). Returns (cost, JᵀWJ,
        JᵀWV, remainder); the matrices are dense for up to _DENSE_MAX_VIEWS views."""
        self._match_table(self.relative(R), with_jacobian)
        args = (loss, scale, robust_hessian, with_jacobian, exact_radial_curvature)
        if self._peer is not None:
            self._submit("sums", *args)
            parts = [self._part_sums(*args, self.block_parts[0])] + self._peer.collect()
        else:
            parts = [self._part_sums(*args, part) for part in self.block_parts]
        cost, sums, excess_sums, any_excess = parts[0]
        for cost_p, sums_p, excess_p, any_p in parts[1:]:
            cost += cost_p
            if sums is not None:
                sums = tuple(a + b for a, b in zip(sums, sums_p))
            if excess_sums is not None:
                excess_sums = tuple(a + b for a, b in zip(excess_sums, excess_p))
            any_excess |= any_p
        if not with_jacobian:
            return cost, None, None, None
        dense = self.n <= _DENSE_MAX_VIEWS
        JtJ, grad = self._assemble(R, sums, dense)
        remainder = self._assemble(R, excess_sums, dense)[0] if any_excess else None
        return cost, JtJ, grad, remainder

    def _part_sums(self, loss: str, scale: float, robust_hessian: bool, with_jacobian: bool,
                   exact_radial_curvature: bool, part: tuple[int, int]):
        """(cost, sums, excess sums, any excess) of :meth:`linearize` over the blocks
        ``self.blocks[part[0]:part[1]]``, from the table of the last :meth:`_match_table`."""
        sums = self._new_sums() if with_jacobian else None
        excess_sums = self._new_sums() if with_jacobian and robust_hessian and exact_radial_curvature else None
        any_excess = False
        cost = 0.0
        for blk, V_blk, _, B in self._block_terms(with_jacobian, self.blocks[part[0]:part[1]]):
            sq = V_blk[0] * V_blk[0] + V_blk[1] * V_blk[1] + V_blk[2] * V_blk[2]
            rho, drho = robust_rho(sq, loss, scale)
            cost += float(rho.sum())
            if with_jacobian:
                alpha = None
                if robust_hessian:
                    beta = robust_curvature(sq, loss, scale)
                    if np.any(beta > 0):
                        alpha = 1.0 - np.sqrt(1.0 - np.clip(beta, 0.0, 1.0))
                self._accumulate(sums, blk, B, V_blk, drho, alpha)
                if excess_sums is not None:
                    excess = radial_excess(sq, loss, scale)
                    if np.any(excess > 0):
                        any_excess = True
                        self._accumulate_rank_one(excess_sums, blk, B, V_blk, drho * excess)
        return cost, sums, excess_sums, any_excess

    def _accumulate_rank_one(self, sums, blk, B: np.ndarray, V_blk: np.ndarray, weight: np.ndarray) -> None:
        """Adds one block's Σ_g w_g q_gᵀ q_g, q_g = v̂_gᵀ J_g (v̂ = V_g / ‖V_g‖), to the
        J_eᵀJ_e sums (diagonal and pair blocks; the gradient sums are left untouched): per
        contribution the row q_c = √w v̂ᵀ B_c, and its blocks are outer products q_cᵀ q_c'."""
        _, diag, off = sums
        s0, s1, g0, g1, p0, p1 = blk
        # only observations with w > 0 (beyond the loss scale: a few percent) contribute
        obs = np.flatnonzero(weight > 0)
        sizes = self.sizes[g0:g1][obs]
        norm = np.sqrt(V_blk[0, obs] ** 2 + V_blk[1, obs] ** 2 + V_blk[2, obs] ** 2)
        scaled = V_blk[:, obs] * (np.sqrt(weight[obs]) / np.where(norm > 0, norm, 1.0))
        # their contributions (positions in the block)
        starts = self.starts[g0 + obs] - s0
        contrib = np.repeat(starts - np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes) + np.arange(sizes.sum())
        Bs = B[:, contrib]
        v_c = [np.repeat(scaled[a], sizes) for a in range(3)]
        q = np.stack([v_c[0] * Bs[c] + v_c[1] * Bs[3 + c] + v_c[2] * Bs[6 + c] for c in range(3)])
        diag += _block_products(q, q, self.edge_sorted[s0:s1][contrib], self.E, symmetric=True)
        if p1 > p0:
            # pairs of those observations, as positions in ``contrib`` (pairs are ordered by
            # observation and contiguous per observation)
            pa = self.pair_a[p0:p1] - s0
            selected = np.zeros(s1 - s0, dtype=bool)
            selected[contrib] = True
            keep = selected[pa]
            if np.any(keep):
                index = np.full(s1 - s0, -1, dtype=np.int64)
                index[contrib] = np.arange(len(contrib))
                qa = q.take(index[pa[keep]], axis=1)
                qb = q.take(index[self.pair_b[p0:p1][keep] - s0], axis=1)
                off += _block_products(qa, qb, self.pair_block[p0:p1][keep], len(off))

    def chain_matrix(self, R: np.ndarray) -> sp.csr_matrix:
        """C (3E x 3n): δ_e = δ_j - R_ij δ_i."""
        return chain_matrix(R, self.edge_views, self.n)

    def _new_sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zeroed J_eᵀWV per edge (E, 3), diagonal blocks (E, 9) and pair blocks (K, 9) of J_eᵀWJ_e."""
        return np.zeros((self.E, 3)), np.zeros((self.E, 9)), np.zeros((len(self.block_keys), 9))

    def _accumulate(self, sums, blk, B: np.ndarray, V_blk: np.ndarray, weight: np.ndarray,
                    alpha: np.ndarray | None) -> None:
        """Adds one block's J_eᵀWV and J_eᵀWJ_e (blocks (e_c, e_c) and (e_c, e_c') of the
        pairs c < c' of each observation) to ``sums``. ``weight`` (g,) = ρ' ≥ 0 per
        observation; ``alpha`` (g,): the curvature correction B_c <- (I - α v̂v̂ᵀ) B_c
        (see :meth:`normal_equations`)."""
        g_edge, diag, off = sums
        s0, s1, g0, g1, p0, p1 = blk
        sizes = self.sizes[g0:g1]
        edges = self.edge_sorted[s0:s1]
        E = self.E
        wV = [np.repeat(V_blk[a] * weight, sizes) for a in range(3)]
        # J_eᵀ W V per edge: Σ_c B_cᵀ w_g V_g
        for c in range(3):
            g_edge[:, c] += np.bincount(edges, weights=B[c] * wV[0] + B[3 + c] * wV[1] + B[6 + c] * wV[2],
                                        minlength=E)
        # √w (I - α v̂v̂ᵀ) B_c once per contribution: the products below then need no weights
        root_w = np.repeat(np.sqrt(weight), sizes)
        Bw = np.empty_like(B)
        if alpha is None:
            np.multiply(B, root_w, out=Bw)
        else:
            norm = np.sqrt(V_blk[0] * V_blk[0] + V_blk[1] * V_blk[1] + V_blk[2] * V_blk[2])
            v_hat = V_blk / np.where(norm > 0, norm, 1.0)
            v_c = [np.repeat(v_hat[a], sizes) for a in range(3)]
            wav = [root_w * np.repeat(alpha * v_hat[a], sizes) for a in range(3)]
            for c in range(3):
                q = v_c[0] * B[c] + v_c[1] * B[3 + c] + v_c[2] * B[6 + c]  # (v̂ᵀ B)_c
                for a in range(3):
                    Bw[3 * a + c] = root_w * B[3 * a + c] - wav[a] * q
        diag += _block_products(Bw, Bw, edges, E, symmetric=True)
        if p1 > p0:
            pa = self.pair_a[p0:p1] - s0
            pb = self.pair_b[p0:p1] - s0
            off += _block_products(Bw.take(pa, axis=1), Bw.take(pb, axis=1), self.pair_block[p0:p1], len(off))

    def _assemble(self, R: np.ndarray, sums, dense: bool):
        """(JᵀWJ, JᵀWV) of the 3n camera parameters from the edge sums, J = J_e C: each edge
        block M at (e, f) (e = (i, j), f = (k, l)) adds C_eᵀ M C_f, i.e. M at views (j, l),
        -M R_f at (j, k), -R_eᵀ M at (i, l) and R_eᵀ M R_f at (i, k) (C_e = [-R_ij at i, I at j])."""
        g_edge, diag, off = sums
        n, E = self.n, self.E
        R_ij = self.relative(R)
        Rt = np.swapaxes(R_ij, 1, 2)
        vi, vj = self.edge_views[:, 0], self.edge_views[:, 1]
        grad = np.zeros((n, 3))
        Rt_g = np.einsum("eab,eb->ea", Rt, g_edge)
        for c in range(3):
            grad[:, c] = np.bincount(vj, weights=g_edge[:, c], minlength=n) - np.bincount(vi, weights=Rt_g[:, c],
                                                                                           minlength=n)
        # blocks (e, f, M): the diagonal ones, the pairs and their transposes
        off_blocks = off.reshape(-1, 3, 3)
        e = np.concatenate([np.arange(E), self.block_row, self.block_col])
        f = np.concatenate([np.arange(E), self.block_col, self.block_row])
        M = np.concatenate([diag.reshape(E, 3, 3), off_blocks, np.swapaxes(off_blocks, 1, 2)])
        MR = M @ R_ij[f]
        data = np.concatenate([M, -MR, -(Rt[e] @ M), Rt[e] @ MR])
        rows = np.concatenate([vj[e], vj[e], vi[e], vi[e]])
        cols = np.concatenate([vj[f], vi[f], vj[f], vi[f]])
        if dense:
            H = np.zeros((n * n, 9))
            for k in range(9):
                H[:, k] = np.bincount(rows * n + cols, weights=data[:, k // 3, k % 3], minlength=n * n)
            return H.reshape(n, n, 3, 3).transpose(0, 2, 1, 3).reshape(3 * n, 3 * n), grad.ravel()
        r3 = np.broadcast_to((3 * rows)[:, None, None] + np.arange(3)[None, :, None], data.shape).ravel()
        c3 = np.broadcast_to((3 * cols)[:, None, None] + np.arange(3)[None, None, :], data.shape).ravel()
        return sp.csc_matrix((data.ravel(), (r3, c3)), shape=(3 * n, 3 * n)), grad.ravel()

    def normal_equations(self, R: np.ndarray, V: np.ndarray, B: np.ndarray, row_weight: np.ndarray,
                         radial_curvature: np.ndarray | None = None):
        """(JᵀWJ (3n x 3n, sparse), JᵀW V (3n,)) with per-observation weights W = ρ' ≥ 0,
        from V and B of :meth:`evaluate`.

        ``radial_curvature`` β_g (G,): the Hessian block of observation g becomes
        ρ' J_gᵀ (I - β_g v̂ v̂ᵀ) J_g (v̂ = V_g / ‖V_g‖), the robust loss's second-order term
        (see :func:`robust_curvature`); the gradient is unchanged. I - β v̂v̂ᵀ = (I - α v̂v̂ᵀ)²
        with α = 1 - sqrt(1 - β): every block is scaled once, B_c <- (I - α v̂ v̂ᵀ) B_c, and
        the pair products stay as they are."""
        sums = self._new_sums()
        alpha = None
        if radial_curvature is not None and np.any(radial_curvature > 0):
            alpha = 1.0 - np.sqrt(1.0 - np.clip(radial_curvature, 0.0, 1.0))
        for blk in self.blocks:
            s0, s1, g0, g1, _, _ = blk
            self._accumulate(sums, blk, B[:, s0:s1], V[g0:g1].T, row_weight[g0:g1],
                             None if alpha is None else alpha[g0:g1])
        return self._assemble(R, sums, dense=False)


def _block_products(Ba: np.ndarray, Bb: np.ndarray, index: np.ndarray, length: int,
                    symmetric: bool = False) -> np.ndarray:
    """Σ over ``index`` of B_aᵀ B_b, (length, 9): columns of 3k stacked rows (k x 3 blocks as
    3k component rows, e.g. the (9, ·) Jacobian blocks or (3, ·) row vectors q);
    ``symmetric`` (Ba is Bb): the 6 upper products only, mirrored."""
    out = np.empty((length, 9))
    rows = range(0, len(Ba), 3)
    for p in range(3):
        for q in range(p if symmetric else 0, 3):
            weights = Ba[p] * Bb[q]
            for k in rows[1:]:
                weights = weights + Ba[k + p] * Bb[k + q]
            out[:, 3 * p + q] = np.bincount(index, weights=weights, minlength=length)
            if symmetric and q > p:
                out[:, 3 * q + p] = out[:, 3 * p + q]
    return out


def chain_matrix(R: np.ndarray, edge_views: np.ndarray, n: int) -> sp.csr_matrix:
    """C (3E x 3n): δ_e = δ_j - R_ij δ_i for left perturbations of both cameras."""
    R_ij = R[edge_views[:, 1]] @ np.swapaxes(R[edge_views[:, 0]], 1, 2)
    E = len(edge_views)
    rows = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, :, None], (E, 3, 3)).ravel()
    cols_j = np.broadcast_to((3 * edge_views[:, 1])[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    cols_i = np.broadcast_to((3 * edge_views[:, 0])[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    data = np.concatenate([np.broadcast_to(np.eye(3), (E, 3, 3)).ravel(), (-R_ij).ravel()])
    return sp.csr_matrix((data, (np.concatenate([rows, rows]), np.concatenate([cols_j, cols_i]))), shape=(3 * E, 3 * n))
