"""The fixed structure of a GRRM problem and its evaluation: per-observation residuals V_ik
(eq:GRRMRes2), their exact Jacobian blocks, and the normal equations accumulated block by
block without forming J."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import scipy.sparse as sp

from rotonly_cli.geometry import kernels
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.grrm.layout import Layout, Part, pairs_in_block
from rotonly_cli.geometry.robust import radial_excess, robust_curvature, robust_rho
from rotonly_cli.geometry.tracks import EVALUATION_PARTS, even_ranges

#: contributions per block in GRRMSystem (blocks of ~1 MB arrays stay in cache, and no
#: per-iteration temporary grows with the problem: arrays above glibc's 32 MB mmap
#: threshold would be page-faulted afresh on every allocation); tests lower it
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


def _summed_view_blocks(n: int, terms) -> sp.csc_matrix:
    """The 3n x 3n sparse sum of 3x3 blocks given as ``terms`` (rows, cols, block maker) of
    view-block addresses and (K, 3, 3) blocks (made one term at a time): the duplicates of a
    view pair summed per address first (a bincount per component), then one BSR matrix of the
    distinct view pairs, so no per-entry triplet of every block is ever made (at 1000 views
    those were ~0.7 GB beside the problem)."""
    keys = [rows * n + cols for rows, cols, _ in terms]
    unique, inverse = np.unique(np.concatenate(keys), return_inverse=True)
    blocks = np.zeros((len(unique), 9))
    start = 0
    for key, (_, _, block) in zip(keys, terms):
        data, where = block().reshape(-1, 9), inverse[start:start + len(key)]
        for k in range(9):
            blocks[:, k] += np.bincount(where, weights=data[:, k], minlength=len(unique))
        start += len(key)
    del keys, inverse
    block_rows = unique // n
    indptr = np.searchsorted(block_rows, np.arange(n + 1))
    return sp.bsr_matrix((blocks.reshape(-1, 3, 3), unique % n, indptr), shape=(3 * n, 3 * n)).tocsc()


class GRRMSystem:
    """The fixed structure of a GRRM problem (:class:`~rotonly_cli.geometry.grrm.layout.Layout`:
    observations, parts, pair-block addressing) and its evaluation.

    Normal equations without a huge J: J = J_e C, where J_e (3G x 3E) holds one 3x3 block
    B_c per contribution (match side c -> its observation g, derivative w.r.t. its edge's
    δ_e) and C (3E x 3n) chains δ_e = δ_j - R_ij δ_i. Then JᵀJ = Cᵀ (J_eᵀ J_e) C with
    J_eᵀ J_e = Σ_g Σ_{c, c' in g} B_cᵀ B_c' at block (e_c, e_c'). Each part fills the table
    of its edges' match terms, and each block of its observations gathers its contributions'
    rows, sums them per observation, generates the pairs of contributions inside each
    observation and adds their products into the pair blocks; nothing per pair is kept.
    Each 3-vector / 3x3 block is held as 1-D component arrays (structure of arrays): a 3x3
    product is 27 elementwise multiply-adds.
    """

    def __init__(self, n: int, edge_views: np.ndarray, batch: pg.EdgeBatch | pg.ObservedMatches, obs_ids: np.ndarray,
                 residual_form: str = "bearing"):
        self.n = n
        self.image_plane = residual_form == "image"
        self.E = batch.num_edges
        self.edge_views = edge_views
        self._peer = None  # the helper process evaluating the second share of the parts (:meth:`parallel`)
        self.processes = 1  # processes the last :meth:`parallel` ran in
        self._peer_batch = None  # the batch the peer has
        self.batch = batch
        self.M = pg.num_matches(batch)
        self.layout = Layout(n, edge_views, batch.offsets, obs_ids, chunk=_CHUNK)
        self.num_groups = self.layout.num_groups
        # the parts of this process and of the helper (EVALUATION_PARTS shares of about equal contributions)
        shares = even_ranges([p.num_contributions for p in self.layout.parts], EVALUATION_PARTS)
        self.shares = [self.layout.parts[a:b] for a, b in shares]
        # the edge where the helper's share of the translation weights begins (half the matches)
        self._weights_split = even_ranges(batch.counts, 2)[0][1] if self.E > 1 else self.E

    def relative(self, R: np.ndarray) -> np.ndarray:
        return R[self.edge_views[:, 1]] @ np.swapaxes(R[self.edge_views[:, 0]], 1, 2)

    @contextmanager
    def parallel(self, peer_class=None):
        """Within: the second share of the parts is evaluated by a helper process, side by
        side with this one (the same numbers). ``peer_class``: how to start it (the class of
        runtime.parallel.ForkedPeer: ``peer_class(handler)`` a context manager with submit /
        collect); None, or one share: one process."""
        if peer_class is None or self._peer is not None or len(self.shares) < 2:
            self.processes = 2 if self._peer is not None else 1
            yield self
            return
        self.processes = 2
        self._peer_batch = self.batch  # the helper starts with it
        with peer_class(self._serve) as peer:
            self._peer = peer
            try:
                yield self
            finally:
                self._peer = None

    def _serve(self, message):
        """The helper's side of :meth:`parallel`: the sums (or residuals, or translation
        weights) of the second share."""
        kind, batch, args = message
        if isinstance(batch, tuple):  # the same matches, other weights
            self.batch = self.batch.with_weights(batch[1])
        elif batch is not None:
            self.batch = batch
        if kind == "residuals":
            return [self._part_residuals(*args, part) for part in self.shares[1]]
        if kind == "weights":
            return translation_weights(args[0], self.batch, self._weights_split)
        return self._share_sums(*args, self.shares[1])

    def _submit(self, kind: str, *args) -> None:
        batch = None
        if self._peer_batch is not self.batch:
            # a batch that differs from the helper's by its weights only sends those
            batch = ("weights", self.batch.weights) if _same_matches(self._peer_batch, self.batch) else self.batch
            self._peer_batch = self.batch
        self._peer.submit((kind, batch, args))

    def translation_weights(self, R: np.ndarray, batch: pg.EdgeBatch | pg.ObservedMatches) -> np.ndarray:
        """:func:`translation_weights` of ``batch`` (this problem's matches, any weights) at
        the rotations R, in two halves (the edges from ``_weights_split`` on in the helper, if
        there is one; in halves either way, so the bits do not depend on it)."""
        R_ij = self.relative(R)
        if self._peer is not None:
            self._peer.submit(("weights", None, (R_ij,)))
        first = translation_weights(R_ij, batch, 0, self._weights_split)
        second = self._peer.collect() if self._peer is not None else \
            translation_weights(R_ij, batch, self._weights_split)
        return np.concatenate([first, second])

    def _part_table(self, part: Part, R_ij: np.ndarray, with_jacobian: bool) -> np.ndarray:
        """The part's per-contribution terms in the order of its edges' matches, one row per
        term (each row contiguous: the chunks write into it and the blocks gather from it
        without a transpose): rows 0-2 the residual (in the camera of the observation), 3 the
        ω numerator, 4-6 its derivative, 7-15 the residual's derivative (7 + 3a + c =
        d res_a / dδ_c), w.r.t. the left perturbation of the contribution's edge; columns of
        side j after those of side i."""
        width = 16 if with_jacobian else 4
        Mp = part.num_matches
        table = np.empty((width, 2 * Mp))
        if len(part.edges) == self.E and isinstance(self.batch, pg.EdgeBatch):
            batch = self.batch
        else:
            batch = self.batch.subset(part.edges)
        for e0, e1, m0, m1, cnt, starts, xi, xj, wk in kernels.edge_chunks(batch, kernels.CHUNK_MATCHES):
            edges = part.edges[e0:e1]
            R_chunk = R_ij[edges]
            terms = self.chunk_terms(R_chunk, edges, cnt, starts, xi, xj, with_jacobian, wk)
            Rm = [np.repeat(R_chunk.reshape(-1, 9)[:, k], cnt) for k in range(9)]  # Rm[3b + a] = R_ij[b, a]
            r = terms["r"]  # 6 arrays: r_i in camera-j axes, then r_j
            side_i = table[:, m0:m1]
            side_j = table[:, Mp + m0:Mp + m1]
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
        return table

    def chunk_terms(self, R_ij: np.ndarray, edges: np.ndarray, cnt: np.ndarray, starts: np.ndarray, xi, xj,
                    with_jacobian: bool, wk: np.ndarray | None) -> dict:
        """The per-match TRRM terms of ``edges`` (global indices) at their relative rotations
        ``R_ij`` (kernels.trrm_chunk_terms): the one place where each edge's t_ij(R_ij) is
        made, so a subclass can study other choices."""
        return kernels.trrm_chunk_terms(R_ij, cnt, starts, xi, xj, with_jacobian, wk)

    def _block_terms(self, part: Part, table: np.ndarray, with_jacobian: bool):
        """Yields, per block of the part: the block, its observations' residuals V (3, g) and
        weight sums S (g,), and with the Jacobian its contributions' blocks B (9, s) w.r.t.
        their edge's δ_e (row a*3+c = dV_a / dδ_c)."""
        for blk in part.blocks:
            s0, s1, g0, g1 = blk
            cols = table.take(part.rows[s0:s1], axis=1)
            res, b = cols[0:3], cols[3]
            sizes = part.sizes[g0:g1]
            seg = np.concatenate([[0], np.cumsum(sizes)[:-1]])
            S_blk = np.add.reduceat(b, seg)
            inv_S = 1.0 / np.where(S_blk > 0, S_blk, 1.0)
            V_blk = np.add.reduceat(b * res, seg, axis=1) * inv_S
            if not with_jacobian:
                yield blk, V_blk, S_blk, None
                continue
            B = np.empty((9, s1 - s0))
            inv_S_c = np.repeat(inv_S, sizes)
            b_over_S = b * inv_S_c
            db, dres = cols[4:7], cols[7:16]
            # dV_g = Σ_c [(res_c - V_g) db_c^T + b_c dres_c] / S_g   (ω = b / S, eq:weight)
            for a in range(3):
                dev = (res[a] - np.repeat(V_blk[a], sizes)) * inv_S_c
                for c in range(3):
                    B[3 * a + c] = dev * db[c] + b_over_S * dres[3 * a + c]
            yield blk, V_blk, S_blk, B

    def _part_residuals(self, R_ij: np.ndarray, with_jacobian: bool, part: Part):
        """(V (3, Gp), S (Gp,), B (9, Cp) or None) of the part's observations."""
        table = self._part_table(part, R_ij, with_jacobian)
        V = np.empty((3, len(part.sizes)))
        S = np.empty(len(part.sizes))
        B = np.empty((9, part.num_contributions)) if with_jacobian else None
        for (s0, s1, g0, g1), V_blk, S_blk, B_blk in self._block_terms(part, table, with_jacobian):
            V[:, g0:g1], S[g0:g1] = V_blk, S_blk
            if with_jacobian:
                B[:, s0:s1] = B_blk
        return V, S, B

    def evaluate(self, R: np.ndarray, with_jacobian: bool):
        """Per-observation residuals V (G, 3) and weight sums S (G,) in the order of the sorted
        observation ids, and optionally the per-contribution Jacobian blocks B (9, 2M) w.r.t.
        their edge's δ_e in the layout's contribution order (row a*3+c of B = dV_a / dδ_c;
        :meth:`contribution_groups`, :meth:`contribution_edges` say whose they are)."""
        R_ij = self.relative(R)
        if self._peer is not None and not with_jacobian:
            self._submit("residuals", R_ij, False)
            pieces = [self._part_residuals(R_ij, False, p) for p in self.shares[0]] + self._peer.collect()
        else:
            pieces = [self._part_residuals(R_ij, with_jacobian, p) for p in self.layout.parts]
        V = np.concatenate([p[0] for p in pieces], axis=1).T
        S = np.concatenate([p[1] for p in pieces])
        B = np.concatenate([p[2] for p in pieces], axis=1) if with_jacobian else None
        return V[self.layout.id_order], S[self.layout.id_order], B

    def contribution_groups(self) -> np.ndarray:
        """(2M,) each contribution's observation (index into :meth:`evaluate`'s V), in B's order."""
        in_layout = np.repeat(np.arange(self.num_groups), np.concatenate([p.sizes for p in self.layout.parts]))
        position = np.empty(self.num_groups, dtype=np.int64)
        position[self.layout.id_order] = np.arange(self.num_groups)
        return position[in_layout]

    def contribution_edges(self) -> np.ndarray:
        """(2M,) each contribution's edge, in B's order."""
        return np.concatenate([p.edge for p in self.layout.parts]).astype(np.int64)

    def linearize(self, R: np.ndarray, loss: str, scale: float, robust_hessian: bool, with_jacobian: bool,
                  exact_radial_curvature: bool = False):
        """Robust cost Σ ρ(‖V_g‖²) at R and, with the Jacobian, the normal equations
        (JᵀWJ, JᵀWV) of all 3n parameters (W = ρ', with the loss's second-order term clamped
        to β <= 1 if ``robust_hessian``), accumulated block by block, and with
        ``exact_radial_curvature`` the remainder Σ ρ'(β - 1)₊ q_gᵀq_g (q_g = v̂_gᵀ J_g) that
        the exact Hessian subtracts (else None). Returns (cost, JᵀWJ, JᵀWV, remainder); the
        matrices are dense for up to _DENSE_MAX_VIEWS views."""
        R_ij = self.relative(R)
        args = (R_ij, loss, scale, robust_hessian, with_jacobian, exact_radial_curvature)
        if self._peer is not None:
            self._submit("sums", *args)
            parts = [self._share_sums(*args, self.shares[0])] + [self._peer.collect()]
        else:
            parts = [self._share_sums(*args, share) for share in self.shares]
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

    def _share_sums(self, R_ij: np.ndarray, loss: str, scale: float, robust_hessian: bool, with_jacobian: bool,
                    exact_radial_curvature: bool, share: list[Part]):
        """(cost, sums, excess sums, any excess) of :meth:`linearize` over the parts ``share``."""
        sums = self._new_sums() if with_jacobian else None
        excess_sums = self._new_sums() if with_jacobian and robust_hessian and exact_radial_curvature else None
        any_excess = False
        cost = 0.0
        for part in share:
            table = self._part_table(part, R_ij, with_jacobian)
            side = (part.rows >= part.num_matches).astype(np.int64) if with_jacobian else None
            for blk, V_blk, _, B in self._block_terms(part, table, with_jacobian):
                sq = V_blk[0] * V_blk[0] + V_blk[1] * V_blk[1] + V_blk[2] * V_blk[2]
                rho, drho = robust_rho(sq, loss, scale)
                cost += float(rho.sum())
                if not with_jacobian:
                    continue
                s0, s1, g0, g1 = blk
                sizes = part.sizes[g0:g1]
                edges = part.edge[s0:s1]
                alpha = None
                if robust_hessian:
                    beta = robust_curvature(sq, loss, scale)
                    if np.any(beta > 0):
                        alpha = 1.0 - np.sqrt(1.0 - np.clip(beta, 0.0, 1.0))
                self._accumulate(sums, sizes, edges, side[s0:s1], B, V_blk, drho, alpha)
                if excess_sums is not None:
                    excess = radial_excess(sq, loss, scale)
                    if np.any(excess > 0):
                        any_excess = True
                        self._accumulate_rank_one(excess_sums, sizes, edges, side[s0:s1], B, V_blk, drho * excess)
            del table, side  # the next part's table is not made beside this one (256 B per match of a part)
        return cost, sums, excess_sums, any_excess

    def _accumulate_rank_one(self, sums, sizes, edges, side, B: np.ndarray, V_blk: np.ndarray,
                             weight: np.ndarray) -> None:
        """Adds one block's Σ_g w_g q_gᵀ q_g, q_g = v̂_gᵀ J_g (v̂ = V_g / ‖V_g‖), to the
        J_eᵀJ_e sums (diagonal and pair blocks; the gradient sums are left untouched): per
        contribution the row q_c = √w v̂ᵀ B_c, and its blocks are outer products q_cᵀ q_c'."""
        _, diag, off = sums
        # only observations with w > 0 (beyond the loss scale: a few percent) contribute
        obs = np.flatnonzero(weight > 0)
        sizes_obs = sizes[obs]
        norm = np.sqrt(V_blk[0, obs] ** 2 + V_blk[1, obs] ** 2 + V_blk[2, obs] ** 2)
        scaled = V_blk[:, obs] * (np.sqrt(weight[obs]) / np.where(norm > 0, norm, 1.0))
        # their contributions (positions in the block)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])[obs]
        contrib = np.repeat(starts - np.concatenate([[0], np.cumsum(sizes_obs)[:-1]]), sizes_obs) + \
            np.arange(sizes_obs.sum())
        Bs = B[:, contrib]
        v_c = [np.repeat(scaled[a], sizes_obs) for a in range(3)]
        q = np.stack([v_c[0] * Bs[c] + v_c[1] * Bs[3 + c] + v_c[2] * Bs[6 + c] for c in range(3)])
        if not len(contrib):
            return
        if self.layout.dense_pair_blocks:
            _view_products(self.layout, q, sizes_obs, edges[contrib], side[contrib], diag, off)
            return
        diag += _block_products(q, q, edges[contrib], self.E, symmetric=True)
        pa, pb = pairs_in_block(sizes_obs)  # positions in ``contrib``
        if len(pa):
            pair_block = self.layout.pair_blocks(edges[contrib], side[contrib], pa, pb)
            off += _block_products(q.take(pa, axis=1), q.take(pb, axis=1), pair_block, len(off))

    def chain_matrix(self, R: np.ndarray) -> sp.csr_matrix:
        """C (3E x 3n): δ_e = δ_j - R_ij δ_i."""
        return chain_matrix(R, self.edge_views, self.n)

    def _new_sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Zeroed J_eᵀWV per edge (E, 3), diagonal blocks (E, 9) and pair blocks (K, 9) of J_eᵀWJ_e."""
        return np.zeros((self.E, 3)), np.zeros((self.E, 9)), np.zeros((self.layout.num_blocks, 9))

    def _accumulate(self, sums, sizes, edges, side, B: np.ndarray, V_blk: np.ndarray,
                    weight: np.ndarray, alpha: np.ndarray | None) -> None:
        """Adds one block's J_eᵀWV and J_eᵀWJ_e (blocks (e_c, e_c) and (e_c, e_c') of the
        pairs c, c' of each observation) to ``sums``. ``weight`` (g,) = ρ' ≥ 0 per observation;
        ``alpha`` (g,): the curvature correction B_c <- (I - α v̂v̂ᵀ) B_c (see
        :meth:`normal_equations`)."""
        g_edge, diag, off = sums
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
        if self.layout.dense_pair_blocks:
            _view_products(self.layout, Bw, sizes, edges, side, diag, off)
            return
        diag += _block_products(Bw, Bw, edges, E, symmetric=True)
        pa, pb = pairs_in_block(sizes)
        if len(pa):
            pair_block = self.layout.pair_blocks(edges, side, pa, pb)
            off += _block_products(Bw.take(pa, axis=1), Bw.take(pb, axis=1), pair_block, len(off))

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
        # the pair blocks that occur (the dense per-view tables hold blocks no observation fills)
        present = np.flatnonzero(np.any(off != 0.0, axis=1))
        off_blocks = off[present].reshape(-1, 3, 3)
        row, col = self.layout.block_row[present], self.layout.block_col[present]
        e = np.concatenate([np.arange(E), row, col])
        f = np.concatenate([np.arange(E), col, row])
        M = np.concatenate([diag.reshape(E, 3, 3), off_blocks, np.swapaxes(off_blocks, 1, 2)])
        del off_blocks, row, col
        MR = M @ R_ij[f]
        # the four view blocks of each (e, f), made one kind at a time
        terms = ((vj[e], vj[f], lambda: M), (vj[e], vi[f], lambda: -MR), (vi[e], vj[f], lambda: -(Rt[e] @ M)),
                 (vi[e], vi[f], lambda: Rt[e] @ MR))
        if dense:
            data = np.concatenate([block() for _, _, block in terms])
            key = np.concatenate([rows * n + cols for rows, cols, _ in terms])
            H = np.zeros((n * n, 9))
            for k in range(9):
                H[:, k] = np.bincount(key, weights=data[:, k // 3, k % 3], minlength=n * n)
            return H.reshape(n, n, 3, 3).transpose(0, 2, 1, 3).reshape(3 * n, 3 * n), grad.ravel()
        return _summed_view_blocks(n, terms), grad.ravel()

    def normal_equations(self, R: np.ndarray, V: np.ndarray, B: np.ndarray, row_weight: np.ndarray,
                         radial_curvature: np.ndarray | None = None):
        """(JᵀWJ (3n x 3n, sparse), JᵀW V (3n,)) with per-observation weights W = ρ' ≥ 0,
        from V and B of :meth:`evaluate` (V, ``row_weight`` and ``radial_curvature`` in its
        order of the observation ids).

        ``radial_curvature`` β_g (G,): the Hessian block of observation g becomes
        ρ' J_gᵀ (I - β_g v̂ v̂ᵀ) J_g (v̂ = V_g / ‖V_g‖), the robust loss's second-order term
        (see :func:`robust_curvature`); the gradient is unchanged. I - β v̂v̂ᵀ = (I - α v̂v̂ᵀ)²
        with α = 1 - sqrt(1 - β): every block is scaled once, B_c <- (I - α v̂ v̂ᵀ) B_c, and
        the pair products stay as they are."""
        sums = self._new_sums()
        alpha = None
        if radial_curvature is not None and np.any(radial_curvature > 0):
            alpha = 1.0 - np.sqrt(1.0 - np.clip(radial_curvature, 0.0, 1.0))
        # to the layout's observation order
        id_index = np.empty(self.num_groups, dtype=np.int64)  # layout position -> place in id order
        id_index[self.layout.id_order] = np.arange(self.num_groups)
        c_offset = 0
        for part in self.layout.parts:
            side = (part.rows >= part.num_matches).astype(np.int64)
            for s0, s1, g0, g1 in part.blocks:
                g = id_index[part.g0 + g0:part.g0 + g1]
                sizes, edges = part.sizes[g0:g1], part.edge[s0:s1]
                self._accumulate(sums, sizes, edges, side[s0:s1], B[:, c_offset + s0:c_offset + s1],
                                 V[g].T, row_weight[g], None if alpha is None else alpha[g])
            c_offset += part.num_contributions
        return self._assemble(R, sums, dense=False)


def translation_weights(R_ij: np.ndarray, batch: pg.EdgeBatch | pg.ObservedMatches, e_lo: int = 0,
                        e_hi: int | None = None) -> np.ndarray:
    """Each match's weight in its edge's t (Σ w θθᵀ), for the matches of edges [e_lo, e_hi)
    (default: all; ``R_ij`` of all the edges): two Huber IRLS rounds of its TRRM residual
    (geometry/trrm.irls_match_weights, per edge), group by group of edges so that no
    per-match table of all the matches is made at once (the numbers are per edge, but other
    groups move them by rounding: 1e-13° in GRRM's end at 1000 views, so a caller whose bits
    must not depend on its processes cuts the edges the same way every time, as
    GRRMSystem.translation_weights does)."""
    from rotonly_cli.geometry.trrm import irls_match_weights

    e_hi = batch.num_edges if e_hi is None else e_hi
    base = int(batch.offsets[e_lo])
    w = np.empty(int(batch.offsets[e_hi]) - base)
    for e0, e1, sub in pg.edge_group_batches(batch, e_lo=e_lo, e_hi=e_hi):
        m0, m1 = int(batch.offsets[e0]) - base, int(batch.offsets[e1]) - base
        w[m0:m1] = irls_match_weights(R_ij[e0:e1], sub, kind="huber")
    return w


def _same_matches(a, b) -> bool:
    """Whether batches ``a`` and ``b`` hold the same match arrays (the same objects), whatever
    their weights."""
    if type(a) is not type(b):
        return False
    names = ("coords", "rows", "offsets") if isinstance(a, pg.ObservedMatches) else ("x_i", "x_j", "offsets")
    return all(getattr(a, name) is getattr(b, name) for name in names)


def _view_products(layout: Layout, Bw: np.ndarray, sizes: np.ndarray, edges: np.ndarray, side: np.ndarray,
                   diag: np.ndarray, off: np.ndarray) -> None:
    """Adds Σ_g Bw_cᵀ Bw_c' over every pair (c, c') of contributions of each observation of a
    block, per view as one matrix product: the observations g of view v in rows, the d_v edges
    at v in columns, X[k g + a, 3 pos(e_c) + c] = (Bw_c)_ac (Bw: (3k, s), k x 3 blocks: the
    Jacobian's 3 x 3, or the remainder's 1 x 3 rows), so XᵀX holds in its block (a, b) the sum
    over the observations of Bw_aᵀ Bw_b of their contributions through the edges at places a
    and b of view v: its diagonal blocks go to ``diag`` (the edge's own products; two
    contributions of one observation through one edge add their cross terms there too), its
    blocks above the diagonal to the dense pair table ``off`` (base[v] + a d_v + b; _assemble
    adds their transposes). The same sums as the products of the pairs, at the speed of a BLAS
    product instead of an array pass per pair component (issue 49: 10⁸ pairs and more at 1000
    views)."""
    k = Bw.shape[0] // 3
    slot = 2 * edges.astype(np.int64) + side
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    obs_view = layout.edge_views[edges[first], side[first]]
    # runs of observations of one view (the layout orders them by view)
    cut = np.flatnonzero(np.r_[True, obs_view[1:] != obs_view[:-1], True])
    for r0, r1 in zip(cut[:-1], cut[1:]):
        v = int(obs_view[r0])
        d = int(layout.deg[v])
        c0 = int(first[r0])
        c1 = int(first[r1]) if r1 < len(first) else len(edges)
        obs_local = np.repeat(np.arange(r1 - r0), sizes[r0:r1])
        pos = layout.inc_pos[slot[c0:c1]]
        X = np.zeros((r1 - r0, d, k, 3))  # [g, place, a, c]
        blocks = Bw[:, c0:c1].T.reshape(-1, k, 3)
        cell = obs_local * d + pos
        if np.bincount(cell, minlength=(r1 - r0) * d).max() <= 1:
            X[obs_local, pos] = blocks
        else:  # an observation matched twice through one edge: its two blocks add up
            np.add.at(X, (obs_local, pos), blocks)
        X = X.transpose(0, 2, 1, 3).reshape(k * (r1 - r0), 3 * d)
        S = (X.T @ X).reshape(d, 3, d, 3).transpose(0, 2, 1, 3)  # [place a, place b, p, q]
        edges_at_v = layout.edges_at(v)
        diag[edges_at_v] += S[np.arange(d), np.arange(d)].reshape(d, 9)
        upper_a, upper_b = np.triu_indices(d, 1)
        off[layout.base[v] + upper_a * d + upper_b] += S[upper_a, upper_b].reshape(-1, 9)


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
