"""Kernels that need no per-match work per iteration: λ_min(Pˢ) from per-edge 9x9 moments
(TRRM's first phase), per-edge medians, the pure-rotation fit and the point moments of scene
identification."""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.kernels.lean import smallest_eigenpair_lean
from rotonly_cli.geometry.kernels.match_table import INV_NXI, LEAN_CHUNK, XI, XJH, MatchTable
from rotonly_cli.geometry.kernels.soa import edge_groups, pinv_shifted
from rotonly_cli.geometry.tracks import ranks_within

# ----------------------------------------------------------------------------- λ_min(Pˢ) from moments
_LEVI = np.zeros((3, 3, 3))
_LEVI[0, 1, 2] = _LEVI[1, 2, 0] = _LEVI[2, 0, 1] = 1.0
_LEVI[0, 2, 1] = _LEVI[2, 1, 0] = _LEVI[1, 0, 2] = -1.0
_GEN = -_LEVI  # _GEN[c] = [e_c]x (hat of the c-th unit vector)
_IU = np.triu_indices(9)


def epipolar_moments(table: MatchTable) -> np.ndarray:
    """Per-edge M = Σ w m mᵀ (E, 9, 9), m = vec(x̂_i x̂_jᵀ) (m[3d + c] = x̂_i,d x̂_j,c), so
    that the bearing-normalised θ̂ = L(R) m and Pˢ = L M Lᵀ (epipolar_from_moments)."""
    E = table.num_edges
    upper = np.empty((len(_IU[0]), E))
    pa, pb = _IU
    for e0, e1 in table.groups:
        m0, m1 = table.offsets[e0], table.offsets[e1]
        d = table.data[:, m0:m1]
        xih = d[XI:XI + 3] * d[INV_NXI]
        xjh = d[XJH:XJH + 3]
        m = (xih[:, None, :] * xjh[None, :, :]).reshape(9, -1)
        wm = m if table.weights is None else m * table.weights[m0:m1]
        starts = table.offsets[e0:e1] - m0
        # rows (a, b >= a) of the upper triangle in _IU order, by broadcasting (no gathered copies)
        prods = np.empty((len(pa), m.shape[1]))
        k = 0
        for a in range(9):
            np.multiply(wm[a], m[a:], out=prods[k:k + 9 - a])
            k += 9 - a
        upper[:, e0:e1] = np.add.reduceat(prods, starts, axis=1)
    M = np.empty((E, 9, 9))
    M[:, pa, pb] = upper.T
    M[:, pb, pa] = upper.T
    return M


def _levi_L(R: np.ndarray) -> np.ndarray:
    """L (E, 3, 9) with θ_a = Σ L[a, 3d + c] x_i,d x_j,c, i.e. L[a, (d, c)] = Σ_b ε_abc R_bd."""
    return np.einsum("abc,ebd->eadc", _LEVI, R).reshape(-1, 3, 9)


def epipolar_from_moments(R: np.ndarray, M: np.ndarray, with_jacobian: bool = True) -> dict:
    """λ_min(Pˢ) of the bearing-normalised θ (= kernels.epipolar_normal_equations' cost),
    its JᵀJ and Jᵀr, from the moments M in O(1) per edge (module comment above)."""
    L = _levi_L(R)
    ML = M @ np.swapaxes(L, 1, 2)  # (E, 9, 3)
    P = L @ ML
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    lam, t = smallest_eigenpair_lean(P[:, 0, 0], P[:, 0, 1], P[:, 0, 2], P[:, 1, 1], P[:, 1, 2], P[:, 2, 2])
    y = np.einsum("eka,ea->ek", ML, t)  # M Lᵀ t (E, 9)
    out = {"cost": np.einsum("ek,ek->e", np.einsum("eak,ea->ek", L, t), y), "t": t}
    if not with_jacobian:
        return out
    # L_c = L([e_c]x R): the derivative of L for R <- exp([δ]x) R along δ_c
    Lc = np.stack([_levi_L(_GEN[c] @ R) for c in range(3)], axis=1)  # (E, 3c, 3a, 9)
    Lct = np.einsum("ecak,ea->eck", Lc, t)  # (L_cᵀ t) (E, 3, 9)
    # dPˢt column c = L_c M Lᵀ t + L M L_cᵀ t
    dPt = np.einsum("ecak,ek->eac", Lc, y) + np.einsum("eka,eck->eac", ML, Lct)
    T = -pinv_shifted(P, lam, t) @ dPt
    G = Lct + np.einsum("eak,eac->eck", L, T)  # J_k[c] = G_c · m_k
    GM = G @ M
    out["JtJ"] = GM @ np.swapaxes(G, 1, 2)
    out["Jtr"] = np.einsum("eck,ek->ec", G, y)
    return out


# ----------------------------------------------------------------------------- robust medians, Procrustes
def segment_median(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """pairwise.segment_median (per-edge upper median, the element of rank ⌊m/2⌋) with one
    ``np.partition`` per bucket of edges of similar size instead of one global sort.

    Rows are padded to a common width with -inf and +inf so that every row's median sits at
    the same column: a row of n values gets K - ⌊n/2⌋ leading -inf, K = max ⌊n/2⌋."""
    values = np.asarray(values, dtype=float)
    counts = np.diff(offsets)
    E = len(counts)
    out = np.zeros(E)
    if E == 0 or values.size == 0:
        return out
    order = np.argsort(counts, kind="stable")
    sorted_counts = counts[order]
    b0 = 0
    while b0 < E:
        # edges whose sizes differ by at most 25 % share a padded block
        b1 = int(np.searchsorted(sorted_counts, sorted_counts[b0] * 1.25, side="right"))
        b1 = max(b1, b0 + 1)
        edges = order[b0:b1]
        n = counts[edges]
        if n[0] == n[-1]:  # equal sizes (sorted): no padding, the median sits at column n // 2
            if edges[-1] - edges[0] == len(edges) - 1:  # consecutive edges (stable sort): a view, no gather
                block = values[offsets[edges[0]]:offsets[edges[-1] + 1]].reshape(len(edges), n[0])
            else:
                block = values[(offsets[:-1][edges][:, None] + np.arange(n[0])[None, :]).ravel()].reshape(
                    len(edges), n[0])
            out[edges] = np.partition(block, n[0] // 2, axis=1)[:, n[0] // 2]
            b0 = b1
            continue
        half = n // 2
        K = int(half.max())
        W = K + int((n - half).max())
        lead = K - half
        block = np.full((len(edges), W), np.inf)
        block[np.arange(W)[None, :] < lead[:, None]] = -np.inf
        rows = np.repeat(np.arange(len(edges)), n)
        within = ranks_within(n)
        src = np.repeat(offsets[:-1][edges], n) + within
        block[rows, np.repeat(lead, n) + within] = values[src]
        out[edges] = np.partition(block, K, axis=1)[:, K]
        b0 = b1
    return out


def rotated_bearing_sq(R: np.ndarray, table: MatchTable) -> np.ndarray:
    """Per-match ‖x̂_j - R x̂_i‖² (eq:PureRotationReprojBearingError, one view), (M,)."""
    sq = np.empty(table.data.shape[1])
    for e0, e1 in table.groups:
        m0, m1 = table.offsets[e0], table.offsets[e1]
        d = table.data[:, m0:m1]
        cnt = table.counts[e0:e1]
        Rr = np.repeat(R[e0:e1].reshape(-1, 9).T, cnt, axis=1)
        # (3, n) blocks: R x_i = R_k0 x_i0 + R_k1 x_i1 + R_k2 x_i2, then x̂_j - (R x_i)/‖x_i‖
        diff = np.multiply(Rr[0::3], d[0])
        diff += np.multiply(Rr[1::3], d[1], out=Rr[1::3])
        diff += np.multiply(Rr[2::3], d[2], out=Rr[2::3])
        diff *= d[INV_NXI]
        np.subtract(d[XJH:XJH + 3], diff, out=diff)
        np.add.reduce(np.multiply(diff, diff, out=diff), axis=0, out=sq[m0:m1])
    return sq


def bearing_cross_moment(table: MatchTable, w: np.ndarray | None = None) -> np.ndarray:
    """H = Σ w x̂_j x̂_iᵀ per edge (E, 3, 3) (orthogonal Procrustes)."""
    E = table.num_edges
    H = np.empty((E, 3, 3))
    for e0, e1 in table.groups:
        m0, m1 = table.offsets[e0], table.offsets[e1]
        d = table.data[:, m0:m1]
        xih = d[XI:XI + 3] * d[INV_NXI]
        xjh = d[XJH:XJH + 3] if w is None else d[XJH:XJH + 3] * w[m0:m1]
        prods = (xjh[:, None, :] * xih[None, :, :]).reshape(9, -1)
        H[e0:e1] = np.add.reduceat(prods, table.offsets[e0:e1] - m0, axis=1).T.reshape(-1, 3, 3)
    return H


def best_pure_rotation(table: MatchTable, robust_iterations: int = 0) -> np.ndarray:
    """pairwise.best_pure_rotation on a MatchTable (same Procrustes and Cauchy rounds)."""
    from rotonly_cli.geometry import so3

    R = so3.project_to_so3(bearing_cross_moment(table))
    for _ in range(robust_iterations):
        sq = rotated_bearing_sq(R, table)
        c2 = np.repeat((3.0 * 1.4826) ** 2 * segment_median(sq, table.offsets) + 1e-30, table.counts)
        R = so3.project_to_so3(bearing_cross_moment(table, 1.0 / (1.0 + sq / c2)))
    return R


def point_moments(batch: pg.EdgeBatch) -> tuple[np.ndarray, np.ndarray]:
    """Gⁱ = Σ X_i X_iᵀ and Gʲ of the z = 1 points per edge, (E, 3, 3) each
    (eq:case2IdentifyingMatrixBasic); the division by z is skipped when z is already 1."""
    E = batch.num_edges
    G = [np.empty((E, 3, 3)), np.empty((E, 3, 3))]
    pa, pb = np.triu_indices(3)
    for e0, e1 in edge_groups(batch.counts, LEAN_CHUNK) if E else []:
        m0, m1 = batch.offsets[e0], batch.offsets[e1]
        starts = batch.offsets[e0:e1] - m0
        for v, x in enumerate((batch.x_i, batch.x_j)):
            X = x[m0:m1].T
            if not np.all(X[2] == 1.0):
                X = X / X[2]
            upper = np.add.reduceat(X[pa] * X[pb], starts, axis=1).T
            G[v][e0:e1, pa, pb] = upper
            G[v][e0:e1, pb, pa] = upper
    return G[0], G[1]
