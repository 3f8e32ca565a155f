"""Fast per-edge kernels for TRRM and the λ_min(Pˢ) phase: cost, JᵀJ and Jᵀr per edge.

Same mathematics as :func:`rotonly_cli.geometry.twoview.trrm_residuals` and
:func:`~rotonly_cli.geometry.twoview.epipolar_residuals` (the readable reference versions,
which also return per-match residuals and Jacobians and are checked against finite
differences in the tests), organised for speed:

* structure of arrays: every 3-vector is three contiguous 1-D arrays, so cross and dot
  products are a handful of elementwise operations instead of strided ``np.cross`` calls;
* the exact Jacobian is built column by column in forward mode (one pass per rotation
  axis), and only the per-edge sums JᵀJ (6 numbers) and Jᵀr (3) are kept;
* edges are processed in groups of about ``CHUNK_MATCHES`` matches so the ~100
  temporaries of a pass stay in cache. The loop is over groups of edges, never over edges.
"""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import twoview as tv

CHUNK_MATCHES = 1 << 15


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _axpy(alpha, a, beta, b):  # alpha a + beta b with per-match scalars
    return (alpha * a[0] + beta * b[0], alpha * a[1] + beta * b[1], alpha * a[2] + beta * b[2])


def _edge_groups(counts: np.ndarray, chunk: int) -> list[tuple[int, int]]:
    """Consecutive edge ranges [e0, e1) of about ``chunk`` matches each."""
    cum = np.cumsum(counts)
    groups = []
    e0 = 0
    E = len(counts)
    while e0 < E:
        base = cum[e0 - 1] if e0 else 0
        e1 = int(np.searchsorted(cum, base + chunk, side="right"))
        e1 = max(e1, e0 + 1)
        groups.append((e0, min(e1, E)))
        e0 = e1
    return groups


def _rep(values: np.ndarray, counts: np.ndarray):
    return np.repeat(values, counts)


def _seg(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    return np.add.reduceat(values, starts)


def _rotate(R: np.ndarray, counts: np.ndarray, x):
    """u = R_e x per match, R (E, 3, 3)."""
    return tuple(_rep(R[:, k, 0], counts) * x[0] + _rep(R[:, k, 1], counts) * x[1] + _rep(R[:, k, 2], counts) * x[2]
                 for k in range(3))


def _pinv_shifted(P: np.ndarray, lam: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(Pˢ - λI)^+ restricted to the complement of t (eigenvector perturbation)."""
    scale = np.trace(P, axis1=1, axis2=2)[:, None, None] + 1e-300
    tt = t[:, :, None] * t[:, None, :]
    return np.linalg.inv(P - lam[:, None, None] * np.eye(3) + scale * tt) - tt / scale


def _ps_from(theta, starts, w=None):
    if w is not None:  # Σ w θ θᵀ
        wt = tuple(w * v for v in theta)
        return _ps_pairs(wt, theta, starts)
    return _ps_pairs(theta, theta, starts)


def _ps_pairs(a, theta, starts):
    s00 = _seg(a[0] * theta[0], starts)
    s01 = _seg(a[0] * theta[1], starts)
    s02 = _seg(a[0] * theta[2], starts)
    s11 = _seg(a[1] * theta[1], starts)
    s12 = _seg(a[1] * theta[2], starts)
    s22 = _seg(a[2] * theta[2], starts)
    return np.stack([np.stack([s00, s01, s02], -1), np.stack([s01, s11, s12], -1),
                     np.stack([s02, s12, s22], -1)], -2)


def _dPt(theta, theta_dot_t, u, xj, xj_dot_u, u_dot_t, t_m, starts, w=None):
    """Σ_k w_k [(θ·t) A + θ (A^T t)^T] with A = u x_j^T - (x_j·u) I, as (E, 3, 3) (columns = δ axes)."""
    E = len(starts)
    out = np.empty((E, 3, 3))
    if w is not None:
        theta_dot_t = w * theta_dot_t
        theta = tuple(w * v for v in theta)
    for c in range(3):
        at_c = xj[c] * u_dot_t - xj_dot_u * t_m[c]  # (A^T t)_c
        for r in range(3):
            col = theta_dot_t * (u[r] * xj[c] - (xj_dot_u if r == c else 0.0)) + theta[r] * at_c
            out[:, r, c] = _seg(col, starts)
    return out


def _du(c, u):
    """d u for δ = e_c: e_c x u."""
    z = np.zeros_like(u[0])
    if c == 0:
        return (z, -u[2], u[1])
    if c == 1:
        return (u[2], z, -u[0])
    return (-u[1], u[0], z)


def _accumulate(J_cols, r, starts, E):
    """Per-edge JᵀJ (E, 3, 3) and Jᵀr (E, 3) from J columns (tuples of row arrays)."""
    JtJ = np.empty((E, 3, 3))
    Jtr = np.empty((E, 3))
    for a in range(3):
        Jtr[:, a] = _seg(sum(ja * ra for ja, ra in zip(J_cols[a], r)), starts)
        for b in range(a, 3):
            v = _seg(sum(ja * jb for ja, jb in zip(J_cols[a], J_cols[b])), starts)
            JtJ[:, a, b] = v
            JtJ[:, b, a] = v
    return JtJ, Jtr


def _trrm_chunk(Rg: np.ndarray, cnt: np.ndarray, starts: np.ndarray, xi, xj, with_jacobian: bool,
                wk: np.ndarray | None = None, t_fixed: np.ndarray | None = None) -> dict:
    """TRRM terms of one edge group, per match: residual rows r (6 arrays: r_i in camera-j
    axes, then r_j), ‖θ‖, validity weight, t per edge and, with the Jacobian, the three
    forward-mode columns J_cols[c] (6 arrays) and d‖θ‖/dδ_c, for R_ij <- exp([δ]x) R_ij.

    ``t_fixed`` (edges, 3): each edge's t_ij (camera j) held as given (unit length, sign
    included; dt/dδ = 0) instead of Pˢ's null vector: the residual of eq:PA3bearing at a known
    translation (a diagnostic of how much of GRRM's error the per-edge translations carry)."""
    u = _rotate(Rg, cnt, xi)
    theta = _cross(u, xj)
    if t_fixed is None:
        P = _ps_from(theta, starts, wk)
        lam, t = tv.smallest_eigenpair(P)
    else:
        t = np.asarray(t_fixed, dtype=float)  # unit already (grrm._validate_translations)
    t_m = tuple(_rep(t[:, k], cnt) for k in range(3))
    xj_x_t = _cross(xj, t_m)
    u_x_t = _cross(u, t_m)
    # chirality sign (twoview._chirality_sign_from); a given t keeps its own
    sign = np.ones(len(t))
    if t_fixed is None:
        depth_i = _dot(theta, xj_x_t)
        depth_j = _dot(theta, u_x_t)
        vote = _seg(((depth_i > 0) & (depth_j > 0)).astype(np.int64) - ((depth_i < 0) & (depth_j < 0)), starts)
        sign = np.where(vote < 0, -1.0, 1.0)
    if np.any(sign < 0):
        t = t * sign[:, None]
        sgn_m = _rep(sign, cnt)
        t_m = tuple(sgn_m * v for v in t_m)
        xj_x_t = tuple(sgn_m * v for v in xj_x_t)
        u_x_t = tuple(sgn_m * v for v in u_x_t)
    a_j = np.sqrt(_dot(xj_x_t, xj_x_t))
    a_i = np.sqrt(_dot(u_x_t, u_x_t))
    b = np.sqrt(_dot(theta, theta))
    s_j = _axpy(a_j, u, b, t_m)
    s_i = _axpy(a_i, xj, -b, t_m)
    n_xj = np.sqrt(_dot(xj, xj))
    n_u = np.sqrt(_dot(u, u))
    n_sj = np.sqrt(_dot(s_j, s_j))
    n_si = np.sqrt(_dot(s_i, s_i))
    valid = (n_sj > 1e-14) & (n_si > 1e-14)
    w = valid.astype(float)
    inv_sj = np.where(valid, 1.0 / np.where(valid, n_sj, 1.0), 0.0)
    inv_si = np.where(valid, 1.0 / np.where(valid, n_si, 1.0), 0.0)
    sj_hat = tuple(v * inv_sj for v in s_j)
    si_hat = tuple(v * inv_si for v in s_i)
    inv_u = 1.0 / n_u
    r = tuple(w * (u[k] * inv_u - si_hat[k]) for k in range(3)) + \
        tuple(w * (xj[k] / n_xj - sj_hat[k]) for k in range(3))
    out = {"r": r, "b": b, "w": w, "t": t}
    if not with_jacobian:
        return out
    xj_dot_u = _dot(xj, u)
    u_dot_t = _dot(u, t_m)
    theta_dot_t = _dot(theta, t_m)
    if t_fixed is None:
        T = -_pinv_shifted(P, lam, t) @ _dPt(theta, theta_dot_t, u, xj, xj_dot_u, u_dot_t, t_m, starts, wk)
    else:
        T = np.zeros((len(t), 3, 3))
    inv_aj = np.where(a_j > 0, 1.0 / np.where(a_j > 0, a_j, 1.0), 0.0)
    inv_ai = np.where(a_i > 0, 1.0 / np.where(a_i > 0, a_i, 1.0), 0.0)
    inv_b = np.where(b > 0, 1.0 / np.where(b > 0, b, 1.0), 0.0)
    J_cols, db_cols = [], []
    for c in range(3):
        du = _du(c, u)
        dtheta = _cross(du, xj)
        dt = tuple(_rep(T[:, k, c], cnt) for k in range(3))
        da_j = _dot(xj_x_t, _cross(xj, dt)) * inv_aj
        db = _dot(theta, dtheta) * inv_b
        d_uxt = _cross(du, t_m)
        u_x_dt = _cross(u, dt)
        da_i = _dot(u_x_t, (d_uxt[0] + u_x_dt[0], d_uxt[1] + u_x_dt[1], d_uxt[2] + u_x_dt[2])) * inv_ai
        ds_j = tuple(da_j * u[k] + a_j * du[k] + db * t_m[k] + b * dt[k] for k in range(3))
        ds_i = tuple(da_i * xj[k] - db * t_m[k] - b * dt[k] for k in range(3))
        pj = _dot(sj_hat, ds_j)
        pi = _dot(si_hat, ds_i)
        col = tuple(w * (du[k] * inv_u - (ds_i[k] - si_hat[k] * pi) * inv_si) for k in range(3)) + \
            tuple(-w * (ds_j[k] - sj_hat[k] * pj) * inv_sj for k in range(3))
        J_cols.append(col)
        db_cols.append(db)
    out["J_cols"] = J_cols
    out["db"] = db_cols
    return out


def _chunks(batch: tv.EdgeBatch, chunk: int):
    counts = batch.counts
    for e0, e1 in _edge_groups(counts, chunk):
        m0, m1 = batch.offsets[e0], batch.offsets[e1]
        xi = tuple(np.ascontiguousarray(batch.x_i[m0:m1, k]) for k in range(3))
        xj = tuple(np.ascontiguousarray(batch.x_j[m0:m1, k]) for k in range(3))
        wk = None if batch.weights is None else np.ascontiguousarray(batch.weights[m0:m1], dtype=float)
        yield e0, e1, m0, m1, counts[e0:e1], batch.offsets[e0:e1] - m0, xi, xj, wk


def _outputs(E: int, with_jacobian: bool):
    """Zeroed per-edge cost (E,), t (E, 3) and, with the Jacobian, JᵀJ (E, 3, 3), Jᵀr (E, 3)."""
    return (np.zeros(E), np.zeros((E, 3)), np.zeros((E, 3, 3)) if with_jacobian else None,
            np.zeros((E, 3)) if with_jacobian else None)


def trrm_normal_equations(R: np.ndarray, batch: tv.EdgeBatch, with_jacobian: bool = True,
                          chunk: int = CHUNK_MATCHES) -> tv.ResidualEvaluation:
    """Per-edge TRRM cost (eq:ROMerr) and, optionally, JᵀJ and Jᵀr (exact Jacobian).

    With ``batch.weights`` w: Pˢ = Σ w θθᵀ and cost Σ w ‖r‖² (weights held fixed: one IRLS
    round of the robust TRRM in geometry/trrm.py).
    """
    cost, t_all, JtJ, Jtr = _outputs(batch.num_edges, with_jacobian)
    for e0, e1, _, _, cnt, starts, xi, xj, wk in _chunks(batch, chunk):
        terms = _trrm_chunk(R[e0:e1], cnt, starts, xi, xj, with_jacobian, wk)
        t_all[e0:e1] = terms["t"]
        r, J_cols = terms["r"], terms.get("J_cols")
        if wk is not None:
            root_w = np.sqrt(wk)
            r = tuple(root_w * v for v in r)
            if with_jacobian:
                J_cols = [tuple(root_w * v for v in col) for col in J_cols]
        cost[e0:e1] = _seg(sum(v * v for v in r), starts)
        if with_jacobian:
            JtJ[e0:e1], Jtr[e0:e1] = _accumulate(J_cols, r, starts, e1 - e0)
    return tv.ResidualEvaluation(residuals=None, cost=cost, t=t_all, JtJ=JtJ, Jtr=Jtr)


def trrm_match_terms(R: np.ndarray, batch: tv.EdgeBatch, with_jacobian: bool = True,
                     chunk: int = CHUNK_MATCHES) -> dict:
    """Per-match TRRM terms for GRRM: ``r`` (M, 6) [r_i in camera-j axes, r_j], ``b`` (M,) = ‖θ‖,
    ``w`` (M,) validity, ``t`` (E, 3) and, with the Jacobian, ``J`` (M, 6, 3) = dr/dδ and
    ``db`` (M, 3) = d‖θ‖/dδ for the left perturbation of each edge's R_ij."""
    M = batch.x_i.shape[0]
    out = {"r": np.empty((M, 6)), "b": np.empty(M), "w": np.empty(M), "t": np.zeros((batch.num_edges, 3))}
    if with_jacobian:
        out["J"] = np.empty((M, 6, 3))
        out["db"] = np.empty((M, 3))
    for e0, e1, m0, m1, cnt, starts, xi, xj, wk in _chunks(batch, chunk):
        terms = _trrm_chunk(R[e0:e1], cnt, starts, xi, xj, with_jacobian, wk)
        out["t"][e0:e1] = terms["t"]
        out["r"][m0:m1] = np.stack(terms["r"], axis=1)
        out["b"][m0:m1] = terms["b"]
        out["w"][m0:m1] = terms["w"]
        if with_jacobian:
            for c in range(3):
                out["J"][m0:m1, :, c] = np.stack(terms["J_cols"][c], axis=1)
                out["db"][m0:m1, c] = terms["db"][c]
    return out


def epipolar_normal_equations(R: np.ndarray, batch: tv.EdgeBatch, with_jacobian: bool = True,
                              chunk: int = CHUNK_MATCHES) -> tv.ResidualEvaluation:
    """Per-edge λ_min(Pˢ) of bearing-normalised θ (twoview.epipolar_residuals), JᵀJ, Jᵀr."""
    cost, t_all, JtJ, Jtr = _outputs(batch.num_edges, with_jacobian)
    for e0, e1, _, _, cnt, starts, xi, xj, wk in _chunks(batch, chunk):
        scale = 1.0 / (np.sqrt(_dot(xi, xi)) * np.sqrt(_dot(xj, xj)))
        u = _rotate(R[e0:e1], cnt, xi)
        theta = tuple(scale * v for v in _cross(u, xj))
        P = _ps_from(theta, starts, wk)
        lam, t = tv.smallest_eigenpair(P)
        t_all[e0:e1] = t
        t_m = tuple(_rep(t[:, k], cnt) for k in range(3))
        e = _dot(theta, t_m)
        cost[e0:e1] = _seg(e * e if wk is None else wk * e * e, starts)
        if not with_jacobian:
            continue
        # A = scale (u x_j^T - (x_j·u) I); dPt as in _dPt with the scaled A
        xj_dot_u = _dot(xj, u)
        u_dot_t = _dot(u, t_m)
        dPt = _dPt(theta, e * scale, u, xj, xj_dot_u, u_dot_t * scale, tuple(scale * v for v in t_m), starts, wk)
        T = -_pinv_shifted(P, lam, t) @ dPt
        J_cols = []
        for c in range(3):
            At_t_c = scale * (xj[c] * u_dot_t - xj_dot_u * t_m[c])
            dt = tuple(_rep(T[:, k, c], cnt) for k in range(3))
            J_cols.append((At_t_c + _dot(theta, dt),))
        if wk is not None:
            root_w = np.sqrt(wk)
            J_cols = [(root_w * col[0],) for col in J_cols]
            e = root_w * e
        JtJ[e0:e1], Jtr[e0:e1] = _accumulate(J_cols, (e,), starts, e1 - e0)
    return tv.ResidualEvaluation(residuals=None, cost=cost, t=t_all, JtJ=JtJ, Jtr=Jtr)


# ============================================================================= lean LM evaluator
# The functions above serve GRRM and the tests (per-match outputs). The TRRM driver in
# geometry/trrm.py only needs per-edge sums, so it uses the leaner evaluator below:
#
# * a MatchTable holds the per-match constants once (x_i, x_j, x̂_j, 1/‖x_i‖, ‖x_i‖², ‖x_j‖²,
#   1/‖x_j‖) as rows of one (13, M) array, so subsets are one gather and chunks are views;
# * everything in one pass per edge group, and scalar identities replace 3-vector
#   products: with u = R x_i (‖u‖ = ‖x_i‖), unit t and the three dots x_j·t, u·t, u·x_j,
#     ‖x_j × t‖² = ‖x_j‖² - (x_j·t)²,   ‖u × t‖² = ‖x_i‖² - (u·t)²,
#     θ·(x_j × t) = (u·x_j)(x_j·t) - ‖x_j‖²(u·t),  θ·(u × t) = ‖x_i‖²(x_j·t) - (u·x_j)(u·t)
#   (chirality depths, eq:crosspruduct1-2), and because t·dt = 0 (unit t; the shifted
#   pseudo-inverse maps into t's complement) the depth derivatives are scalars times
#   x_j·dt and u·dt;
# * the sign of t enters only through ‖θ‖ t, so it is carried as a per-match sign of ‖θ‖;
# * the Jacobian is needed per edge only through JᵀJ and Jᵀr; an edge whose LM step will
#   end it if accepted is evaluated without it (trrm.py);
# * at ~16k matches per group a numpy call costs about as much in interpreter overhead as in
#   arithmetic, so the pass is organised to make fewer calls: 3-vectors are (3, n) blocks
#   (one call per vector operation), temporaries are rows of one scratch block (out=), the
#   closed-form eigenproblems of several groups are solved in one call (_lean_head, then
#   _head_eigen, then _lean_group), and a group whose edges share a mode is one call on its
#   contiguous slice. Every rewrite keeps the order of the floating-point operations, so
#   results are bit-identical to the per-component expressions written in the comments.
#
# The λ_min(Pˢ) phase needs no per-match work per iteration at all: θ = L(R) m with
# m = vec(x_i x_jᵀ) (9 numbers per match) and L linear in R, so Pˢ(R) = L M Lᵀ with the
# per-edge moment M = Σ w m mᵀ (Kneip & Lynen's observation), and so are dPˢt and JᵀJ.

XI, XJ, XJH, INV_NXI, NXI2, NXJ2, INV_NXJ = 0, 3, 6, 9, 10, 11, 12
TABLE_ROWS = 13
#: matches per edge group of the lean evaluator (measured: 8k-32k within 5 %; 16k best)
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
        self.groups = _edge_groups(self.counts, chunk) if len(self.counts) else []
        self._group_slices: list | None = None

    @classmethod
    def from_batch(cls, batch: tv.EdgeBatch, weights: np.ndarray | None = None,
                   chunk: int = LEAN_CHUNK) -> "MatchTable":
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
        counts = self.counts[edges]
        starts = self.offsets[:-1][edges]
        within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        return np.repeat(starts, counts) + within

    def subset(self, edges: np.ndarray) -> "MatchTable":
        edges = np.asarray(edges, dtype=np.int64)
        idx = self.match_index(edges)
        offsets = np.concatenate([[0], np.cumsum(self.counts[edges])])
        return MatchTable(self.data[:, idx], offsets, None if self.weights is None else self.weights[idx],
                          self.match_pos[idx], self.chunk)

    def with_weights(self, weights: np.ndarray | None) -> "MatchTable":
        return MatchTable(self.data, self.offsets, weights, self.match_pos, self.chunk)


def smallest_eigenpair_lean(p00, p01, p02, p11, p12, p22, rel_tol: float = 1e-8):
    """twoview.smallest_eigenpair on the six entries of symmetric 3x3 matrices: the same
    Cardano root (eq:minlambda), eq:anaTset vector with the longest ξ, two Rayleigh passes
    and the eigh fallback near a double root, in component arithmetic (few numpy calls for
    the small edge groups of one pass)."""
    mean = (p00 + p11 + p22) * (1.0 / 3.0)
    b00, b11, b22 = p00 - mean, p11 - mean, p22 - mean
    o2 = p01 * p01 + p02 * p02 + p12 * p12
    s2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * o2) * (1.0 / 6.0)
    s = np.sqrt(s2)
    inv_s = 1.0 / np.where(s > 0, s, 1.0)
    det = b00 * (b11 * b22 - p12 * p12) - p01 * (p01 * b22 - p12 * p02) + p02 * (p01 * p12 - b11 * p02)
    half_det = 0.5 * det * inv_s * inv_s * inv_s
    phi = np.arccos(np.clip(half_det, -1.0, 1.0)) * (1.0 / 3.0)
    lam = mean + 2.0 * s * np.cos(phi + 2.0 * np.pi / 3.0)
    fro2 = p00 * p00 + p11 * p11 + p22 * p22 + 2.0 * o2
    thresh = (rel_tol ** 2) * fro2 * fro2
    for _ in range(2):
        a00, a11, a22 = p00 - lam, p11 - lam, p22 - lam
        # ξ = rows (0,1), (0,2), (1,2) of P - λI crossed
        x0 = (p01 * p12 - p02 * a11, p02 * p01 - a00 * p12, a00 * a11 - p01 * p01)
        x1 = (p01 * a22 - p02 * p12, p02 * p02 - a00 * a22, a00 * p12 - p01 * p02)
        x2 = (a11 * a22 - p12 * p12, p12 * p02 - p01 * a22, p01 * p12 - a11 * p02)
        n0 = x0[0] * x0[0] + x0[1] * x0[1] + x0[2] * x0[2]
        n1 = x1[0] * x1[0] + x1[1] * x1[1] + x1[2] * x1[2]
        n2 = x2[0] * x2[0] + x2[1] * x2[1] + x2[2] * x2[2]
        # argmax with numpy's tie rule (first maximum)
        use1 = n1 > n0
        best_n = np.where(use1, n1, n0)
        use2 = n2 > best_n
        best_n = np.where(use2, n2, best_n)
        v = [np.where(use2, x2[k], np.where(use1, x1[k], x0[k])) for k in range(3)]
        ok = best_n > thresh
        inv = np.where(ok, 1.0 / np.sqrt(np.where(ok, best_n, 1.0)), 0.0)
        v = [vk * inv for vk in v]
        rq = (p00 * v[0] * v[0] + p11 * v[1] * v[1] + p22 * v[2] * v[2]
              + 2.0 * (p01 * v[0] * v[1] + p02 * v[0] * v[2] + p12 * v[1] * v[2]))
        lam = np.where(ok, rq, lam)
    t = np.stack(v, axis=-1)
    if not np.all(ok):
        bad = ~ok
        P = np.stack([np.stack([p00, p01, p02], -1), np.stack([p01, p11, p12], -1),
                      np.stack([p02, p12, p22], -1)], -2)[bad]
        w, V = np.linalg.eigh(P)
        lam[bad] = w[:, 0]
        t[bad] = V[:, :, 0]
    return lam, t


def _pinv_times(P6, lam: np.ndarray, t: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(Pˢ - λI)^+ D on the complement of t (as _pinv_shifted), P6 the six entries."""
    E = len(lam)
    P = np.empty((E, 3, 3))
    P[:, 0, 0], P[:, 0, 1], P[:, 0, 2] = P6[0], P6[1], P6[2]
    P[:, 1, 0], P[:, 1, 1], P[:, 1, 2] = P6[1], P6[3], P6[4]
    P[:, 2, 0], P[:, 2, 1], P[:, 2, 2] = P6[2], P6[4], P6[5]
    return _pinv_shifted(P, lam, t) @ D


COST, GRADIENT, NORMAL = 0, 1, 2  #: what _lean_group computes: cost; + Jᵀr; + JᵀJ and Jᵀr


#: edge groups whose Pˢ eigenproblems are solved in one call (the closed form is ~200 numpy
#: calls whatever the number of edges, so per group it was ~8 % of a pass); their heads (13
#: rows of matches each) stay alive meanwhile. Measured (CPU time, 1M matches): 4-8 best,
#: 16 and more slower again (the heads leave the cache before their second use)
EIGEN_BATCH_GROUPS = 4


def _lean_head(R: np.ndarray, cnt: np.ndarray, starts: np.ndarray, d: np.ndarray, w: np.ndarray | None,
               unit_theta: bool, plain_ps: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """First part of a pass: ``head`` (13, n) = u = R x_i (3), θ = u × x_j (3), ‖θ‖², pw θ (3)
    (rows 7-9 unused when pw is None), 3 scratch rows; the Pˢ weights ``pw`` and the per-edge
    Pˢ sums (6, E) (12 with ``plain_ps`` and weights: the unweighted sums follow)."""
    n = d.shape[1]
    head = np.empty((13, n))
    u, th, bb, tmp3 = head[0:3], head[3:6], head[6], head[10:13]
    Rr = np.repeat(R.reshape(-1, 9).T, cnt, axis=1)  # Rr[3k + c] = R_kc per match
    xi, xj = d[XI:XI + 3], d[XJ:XJ + 3]
    np.multiply(Rr[0::3], xi[0], out=u)  # u_k = R_k0 x_i0 + R_k1 x_i1 + R_k2 x_i2
    np.multiply(Rr[1::3], xi[1], out=tmp3)
    u += tmp3
    np.multiply(Rr[2::3], xi[2], out=tmp3)
    u += tmp3
    _cross_into(th, u, xj, tmp3[0])  # θ = u × x_j
    _rowsum_into(bb, np.multiply(th, th, out=tmp3))  # ‖θ‖²
    pw = 1.0 / np.maximum(bb, 1e-300) if unit_theta else w
    wt = th if pw is None else np.multiply(th, pw, out=head[7:10])
    nsum = 12 if plain_ps and pw is not None else 6
    prods = np.empty((nsum, n))
    np.multiply(th, wt[0], out=prods[0:3])  # wt_0 θ_0, wt_0 θ_1, wt_0 θ_2, wt_1 θ_1, wt_1 θ_2, wt_2 θ_2
    np.multiply(th[1:], wt[1], out=prods[3:5])
    np.multiply(th[2], wt[2], out=prods[5])
    if nsum == 12:
        np.multiply(th, th[0], out=prods[6:9])
        np.multiply(th[1:], th[1], out=prods[9:11])
        np.multiply(th[2], th[2], out=prods[11])
    return head, pw, np.add.reduceat(prods, starts, axis=1)


def _head_eigen(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """λ_min and null vector of the Pˢ sums (6 or 12 rows, edges along axis 1) and the null
    vector of the unweighted Pˢ (the same one when there are 6 rows)."""
    lam, t = smallest_eigenpair_lean(*sums[:6])
    t_plain = t if sums.shape[0] == 6 else smallest_eigenpair_lean(*sums[6:])[1]
    return lam, t, t_plain


def _lean_group(R: np.ndarray, cnt: np.ndarray, starts: np.ndarray, d: np.ndarray, w: np.ndarray | None,
                mode: int, unit_theta: bool, out: dict, rows: np.ndarray | slice, sq_out: np.ndarray | None,
                plain_ps: bool, pre: tuple | None = None) -> None:
    """TRRM terms of one edge group (edges ``rows`` of the outputs), one pass.

    Pˢ weights: 1/‖θ‖² with ``unit_theta`` (each match one vote), else ``w`` (or 1).
    Residual weights: ``w`` (or 1) times validity. ``sq_out`` receives the per-match
    validity-masked ‖r‖² (without ``w``), the input of the IRLS weights. ``pre``: the
    group's (_lean_head, _head_eigen) results when the caller batched the eigenproblems.

    3-vectors are (3, n) blocks of one scratch array, so a vector operation is one numpy call
    (a third of the calls of per-component arrays, no allocation); a dot product is a product
    block summed over its rows, which numpy adds row after row: the same operation order, and
    so the same bits, as the per-component expressions in the comments."""
    if pre is None:
        head, pw, sums = _lean_head(R, cnt, starts, d, w, unit_theta, plain_ps)
        eig = _head_eigen(sums)
    else:
        (head, pw, sums), eig = pre
    lam, t, t_plain = eig
    n = d.shape[1]
    work = np.empty((45, n))
    u, th, bb = head[0:3], head[3:6], head[6]
    wt = th if pw is None else head[7:10]
    tm, tmp3 = work[0:3], work[3:6]
    sj, si, r = work[6:9], work[9:12], work[12:18]  # r: r_i (3), r_j (3)
    hj, hi, uh = work[18:21], work[21:24], work[24:27]
    ux, xt, ut, aj, ai, b, bs, nsj, nsi, isj, isi, tmp = work[27:39]
    xj = d[XJ:XJ + 3]
    u0, u1, u2 = u
    xj0, xj1, xj2 = xj
    th0, th1, th2 = th
    P6 = sums[:6]
    if plain_ps:
        out["ps"][rows] = sums[-6:].T
    ni2, nj2 = d[NXI2], d[NXJ2]
    _rowsum_into(ux, np.multiply(u, xj, out=tmp3))

    def chirality(t: np.ndarray, tm: np.ndarray, xt: np.ndarray, ut: np.ndarray) -> np.ndarray:
        """t per match, x_j·t, u·t (into ``tm``, ``xt``, ``ut``) and the chirality sign per edge
        (twoview.chirality_sign): the depths in views i and j from the dot identities."""
        tm[:] = np.repeat(t.T, cnt, axis=1)
        _rowsum_into(xt, np.multiply(xj, tm, out=tmp3))
        _rowsum_into(ut, np.multiply(u, tm, out=tmp3))
        depth_i = ux * xt - nj2 * ut
        depth_j = ni2 * xt - ux * ut
        # +1 in front of both cameras, -1 behind both, else 0 (NaN compares false either way)
        both = (np.minimum(depth_i, depth_j) > 0).view(np.int8) - (np.maximum(depth_i, depth_j) < 0).view(np.int8)
        vote = np.add.reduceat(both, starts, dtype=np.int64)
        return np.where(vote < 0, -1.0, 1.0)

    if plain_ps:  # t of the plain Pˢ with its chirality sign (= twoview.translation_directions)
        out["t_plain"][rows] = t_plain * chirality(t_plain, tm, xt, ut)[:, None]
    sign = chirality(t, tm, xt, ut)
    t0, t1, t2 = tm
    out["t"][rows] = t * sign[:, None]
    sg = np.repeat(sign, cnt)
    np.multiply(xt, xt, out=aj)  # ‖x_j × t‖ = sqrt(‖x_j‖² - (x_j·t)²)
    np.subtract(nj2, aj, out=aj)
    np.maximum(aj, 0.0, out=aj)
    np.sqrt(aj, out=aj)
    np.multiply(ut, ut, out=ai)  # ‖u × t‖
    np.subtract(ni2, ai, out=ai)
    np.maximum(ai, 0.0, out=ai)
    np.sqrt(ai, out=ai)
    np.sqrt(bb, out=b)
    np.multiply(b, sg, out=bs)  # ‖θ‖ with the sign of t
    bt = np.multiply(tm, bs, out=tmp3)
    np.multiply(u, aj, out=sj)  # Y^j = a_j u + bs t (eq:PA1)
    sj += bt
    np.multiply(xj, ai, out=si)  # R Y^i = a_i x_j - bs t
    si -= bt
    _rowsum_into(nsj, np.multiply(sj, sj, out=tmp3))
    np.sqrt(nsj, out=nsj)
    _rowsum_into(nsi, np.multiply(si, si, out=tmp3))
    np.sqrt(nsi, out=nsi)
    valid = (nsj > 1e-14) & (nsi > 1e-14)  # a match on the baseline has no prediction
    np.maximum(nsj, 1e-14, out=isj)
    np.divide(1.0, isj, out=isj)
    np.maximum(nsi, 1e-14, out=isi)
    np.divide(1.0, isi, out=isi)
    np.multiply(sj, isj, out=hj)
    np.multiply(si, isi, out=hi)
    inv_ni = d[INV_NXI]
    np.multiply(u, inv_ni, out=uh)
    np.subtract(uh, hi, out=r[0:3])
    np.subtract(d[XJH:XJH + 3], hj, out=r[3:6])
    sq = _rowsum_into(np.empty(n) if sq_out is None else sq_out, np.multiply(r, r, out=work[39:45]))
    sq *= valid
    hj0, hj1, hj2 = hj
    hi0, hi1, hi2 = hi
    uh0, uh1, uh2 = uh
    ri0, ri1, ri2, rj0, rj1, rj2 = r
    rw = valid if w is None else w * valid  # residual weight
    if mode == COST:
        out["cost"][rows] = np.add.reduceat(sq if w is None else w * sq, starts)
        return
    # dt/dδ = -(Pˢ - λI)^+ (dPˢ t)/dδ, dPˢ t = Σ pw [(θ·t) A + θ (Aᵀt)ᵀ], A = u x_jᵀ - (u·x_j) I
    e = _rowsum_into(np.empty(n), np.multiply(th, tm, out=tmp3))
    pe = e if pw is None else pw * e
    pu = np.multiply(u, pe)
    pux = pe * ux
    At = np.multiply(xj, ut)  # Aᵀt = x_j (u·t) - (u·x_j) t
    np.multiply(tm, ux, out=tmp3)
    At -= tmp3
    acc = np.empty((10, n))
    for k in range(3):  # acc[3k + c] = pu_k x_j,c + wt_k (Aᵀt)_c - [k = c] pux
        np.multiply(xj, pu[k], out=acc[3 * k:3 * k + 3])
        np.multiply(At, wt[k], out=tmp3)
        acc[3 * k:3 * k + 3] += tmp3
        acc[4 * k] -= pux
    dPt = np.add.reduceat(acc[:9], starts, axis=1).T.reshape(-1, 3, 3)
    T = -_pinv_times(P6, lam, t, dPt)  # unsigned t; the sign rides on bs and kb
    if mode == GRADIENT:
        _adjoint_gradient(locals(), acc, out, rows)
        return
    _normal_equations(locals(), acc, out, rows)


def _rowsum_into(dst: np.ndarray, block: np.ndarray) -> np.ndarray:
    """dst = block[0] + block[1] + ... (numpy reduces axis 0 of a C-contiguous block row after
    row, so the order is that of the written-out sum)."""
    return np.add.reduce(block, axis=0, out=dst)


def _cross_into(dst: np.ndarray, a, b, tmp: np.ndarray) -> np.ndarray:
    """dst = a × b per match (rows of (3, n) blocks), as a_1 b_2 - a_2 b_1, ..."""
    for k, (p, q) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(a[p], b[q], out=dst[k])
        np.multiply(a[q], b[p], out=tmp)
        dst[k] -= tmp
    return dst


def _dot3_into(dst: np.ndarray, a, b, tmp: np.ndarray) -> np.ndarray:
    """dst = a[0] b[0] + a[1] b[1] + a[2] b[2] (left to right, as the expression), no allocation."""
    np.multiply(a[0], b[0], out=dst)
    np.multiply(a[1], b[1], out=tmp)
    dst += tmp
    np.multiply(a[2], b[2], out=tmp)
    dst += tmp
    return dst


#: matches per block of the Jacobian stage of a NORMAL pass (its ~60 live rows are one scratch
#: block reused by every block). Measured on 1000 x 1000 Standard edges (CPU time, best of
#: 11, loaded machine): 4k and 8k blocks were 5-15 % slower than whole 16k groups (numpy call
#: overhead outweighs the L2 fit), and 64k groups twice as slow (L3 overflow)
NORMAL_BLOCK = 1 << 14
_NORMAL_INPUTS = ("u0", "u1", "u2", "xj0", "xj1", "xj2", "t0", "t1", "t2", "th0", "th1", "th2", "hj0", "hj1", "hj2",
                  "hi0", "hi1", "hi2", "uh0", "uh1", "uh2", "ri0", "ri1", "ri2", "rj0", "rj1", "rj2",
                  "aj", "ai", "b", "bs", "sg", "xt", "ut", "ux", "isj", "isi", "rw", "sq")


def _normal_equations(v: dict, acc: np.ndarray, out: dict, rows: np.ndarray) -> None:
    """JᵀJ, Jᵀr and the cost of one edge group from the forward pass of _lean_group (its locals
    ``v``): the three forward-mode Jacobian columns (6 rows each), then the per-edge sums.

    The per-match work runs in blocks of NORMAL_BLOCK matches (edges may straddle blocks: the
    per-match products land in ``acc`` and are summed per edge at the end), every temporary
    written with ``out=`` into one scratch block reused by all blocks. The order of the
    floating-point operations is that of the plain expressions in the comments (same bits)."""
    n = len(v["u0"])
    Tm = np.repeat(v["T"].reshape(-1, 9).T, v["cnt"], axis=1)  # Tm[3k + c] = dt_k / dδ_c
    block = min(n, NORMAL_BLOCK)
    work = np.empty((44, block))
    inputs = {name: v[name] for name in _NORMAL_INPUTS}
    if v["rw"].dtype != float:
        inputs["rw"] = v["rw"].astype(float)
    for m0 in range(0, n, block):
        m1 = min(n, m0 + block)
        blk = {name: x[m0:m1] for name, x in inputs.items()}
        _normal_block(blk, Tm[:, m0:m1], acc[:, m0:m1], work[:, :m1 - m0])
    sums = np.add.reduceat(acc, v["starts"], axis=1)
    out["cost"][rows] = sums[9]
    JtJ = out["JtJ"]
    JtJ[rows, 0, 0], JtJ[rows, 1, 1], JtJ[rows, 2, 2] = sums[0], sums[3], sums[5]
    JtJ[rows, 0, 1] = JtJ[rows, 1, 0] = sums[1]
    JtJ[rows, 0, 2] = JtJ[rows, 2, 0] = sums[2]
    JtJ[rows, 1, 2] = JtJ[rows, 2, 1] = sums[4]
    out["Jtr"][rows] = sums[6:9].T


#: du = e_c × u has two non-zero entries: (component k, sign, index of u) for each c
_DU_TERMS = (((1, -1, 2), (2, 1, 1)), ((0, 1, 2), (2, -1, 0)), ((0, -1, 1), (1, 1, 0)))
_DOT_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _normal_block(v: dict, Tm: np.ndarray, acc: np.ndarray, work: np.ndarray) -> None:
    """Per-match products of one block: acc[0:6] = w J_aᵀJ_b (upper triangle), acc[6:9] = w J_aᵀr,
    acc[9] = w ‖r‖²; ``work`` (44, block) scratch."""
    u, xj, t = (v["u0"], v["u1"], v["u2"]), (v["xj0"], v["xj1"], v["xj2"]), (v["t0"], v["t1"], v["t2"])
    th, uh = (v["th0"], v["th1"], v["th2"]), (v["uh0"], v["uh1"], v["uh2"])
    hj, hi = (v["hj0"], v["hj1"], v["hj2"]), (v["hi0"], v["hi1"], v["hi2"])
    bs, isj, isi, rw = v["bs"], v["isj"], v["isi"], v["rw"]
    J = work[:18].reshape(3, 6, -1)  # J[c] = dr/dδ_c: rows r_i (3), r_j (3)
    ka_j, ka_i, kb, tmp, da_j, da_i, db, pj, pi = work[18:27]
    q, dj, di, uxt, au = work[27:30], work[30:33], work[33:36], work[36:39], work[39:42]
    u0, u1, u2 = u
    t0, t1, t2 = t
    # ka_j = -x_j·t / a_j (da_j = ka_j (x_j·dt)), ka_i = -u·t / a_i (da_i = ka_i ((u × t)·δ + u·dt)),
    # kb = -(u·x_j) sg / ‖θ‖ (d(±‖θ‖) = kb θ·δ); zero where the norm is zero
    for k_out, num, den in ((ka_j, v["xt"], v["aj"]), (ka_i, v["ut"], v["ai"]), (kb, v["ux"], v["b"])):
        np.maximum(den, 1e-300, out=tmp)
        np.greater(den, 0, out=k_out)
        k_out /= tmp
        np.negative(num, out=tmp)
        k_out *= tmp  # (-num) * inv
    kb *= v["sg"]
    for k, (a0, b0, a1, b1) in enumerate(((u1, t2, u2, t1), (u2, t0, u0, t2), (u0, t1, u1, t0))):
        np.multiply(a0, b0, out=uxt[k])  # u × t
        np.multiply(a1, b1, out=tmp)
        uxt[k] -= tmp
        np.multiply(v["aj"], u[k], out=au[k])
    for c in range(3):
        Tc = (Tm[c], Tm[3 + c], Tm[6 + c])
        _dot3_into(da_j, xj, Tc, tmp)  # da_j = ka_j (x_j·T_c)
        da_j *= ka_j
        np.multiply(u0, Tc[0], out=tmp)  # da_i = ka_i ((u × t)_c + u·T_c)
        np.add(uxt[c], tmp, out=da_i)
        np.multiply(u1, Tc[1], out=tmp)
        da_i += tmp
        np.multiply(u2, Tc[2], out=tmp)
        da_i += tmp
        da_i *= ka_i
        np.multiply(kb, th[c], out=db)
        for k in range(3):
            np.multiply(db, t[k], out=q[k])  # q = db t + bs T_c
            np.multiply(bs, Tc[k], out=tmp)
            q[k] += tmp
            np.multiply(da_j, u[k], out=dj[k])  # ds_j = (da_j u + a_j du) + q
            np.multiply(da_i, xj[k], out=di[k])  # ds_i = da_i x_j - q
            di[k] -= q[k]
        for k, sign, m in _DU_TERMS[c]:
            if sign > 0:
                dj[k] += au[m]
            else:
                dj[k] -= au[m]
        for k in range(3):
            dj[k] += q[k]
        _dot3_into(pj, hj, dj, tmp)  # ŝ_j·ds_j
        _dot3_into(pi, hi, di, tmp)
        for k in range(3):
            row = J[c, 3 + k]  # (ŝ_j (ŝ_j·ds_j) - ds_j) / ‖s_j‖
            np.multiply(hj[k], pj, out=row)
            row -= dj[k]
            row *= isj
            row = J[c, k]  # (ŝ_i (ŝ_i·ds_i) - ds_i) / ‖s_i‖ + du/‖u‖, du/‖u‖ = e_c × û
            np.multiply(hi[k], pi, out=row)
            row -= di[k]
            row *= isi
        for k, sign, m in _DU_TERMS[c]:
            if sign > 0:
                J[c, k] += uh[m]
            else:
                J[c, k] -= uh[m]
    r = (v["ri0"], v["ri1"], v["ri2"], v["rj0"], v["rj1"], v["rj2"])
    # w (a_0 b_0 + ... + a_5 b_5), left to right
    for k, (a, b) in enumerate([(J[p], J[q_]) for p, q_ in _DOT_PAIRS] + [(J[c], r) for c in range(3)]):
        dst = acc[k]
        np.multiply(a[0], b[0], out=dst)
        for i in range(1, 6):
            np.multiply(a[i], b[i], out=tmp)
            dst += tmp
        dst *= rw
    np.multiply(rw, v["sq"], out=acc[9])


def _adjoint_gradient(v: dict, acc: np.ndarray, out: dict, rows: np.ndarray) -> None:
    """Jᵀr = ½ ∇_δ Σ w ‖r‖² by reverse mode through the forward pass of _lean_group (its
    locals ``v``): about a third of the work of the three forward-mode Jacobian columns.

    Adjoints (x̄ = ∂f/∂x, f = ½ Σ w ‖r‖²): ŝ = s/‖s‖ gives s̄ = -(w/‖s‖)(r - ŝ(ŝ·r)); then
    through s_j = a_j u + b_s t, s_i = a_i x_j - b_s t, a_j = ‖x_j × t‖, a_i = ‖u × t‖,
    b = ‖θ‖ (x_j × θ̄ = (b̄/b)(‖x_j‖² u - (u·x_j) x_j)); finally du = δ × u gives u × ū,
    and dt = T δ gives Tᵀ Σ t̄."""
    u0, u1, u2, xj0, xj1, xj2 = v["u0"], v["u1"], v["u2"], v["xj0"], v["xj1"], v["xj2"]
    t0, t1, t2 = v["t0"], v["t1"], v["t2"]
    hj0, hj1, hj2, hi0, hi1, hi2 = v["hj0"], v["hj1"], v["hj2"], v["hi0"], v["hi1"], v["hi2"]
    rj0, rj1, rj2, ri0, ri1, ri2 = v["rj0"], v["rj1"], v["rj2"], v["ri0"], v["ri1"], v["ri2"]
    rw, aj, ai, b, bs, sg = v["rw"], v["aj"], v["ai"], v["b"], v["bs"], v["sg"]
    xt, ut, ux, nj2 = v["xt"], v["ut"], v["ux"], v["nj2"]
    kj = -(rw * v["isj"])
    alpha = hj0 * rj0 + hj1 * rj1 + hj2 * rj2
    sjb = ((rj0 - hj0 * alpha) * kj, (rj1 - hj1 * alpha) * kj, (rj2 - hj2 * alpha) * kj)
    ki = -(rw * v["isi"])
    alpha = hi0 * ri0 + hi1 * ri1 + hi2 * ri2
    sib = ((ri0 - hi0 * alpha) * ki, (ri1 - hi1 * alpha) * ki, (ri2 - hi2 * alpha) * ki)
    ajb = u0 * sjb[0] + u1 * sjb[1] + u2 * sjb[2]
    aib = xj0 * sib[0] + xj1 * sib[1] + xj2 * sib[2]
    dsb = (sjb[0] - sib[0], sjb[1] - sib[1], sjb[2] - sib[2])
    bsb = t0 * dsb[0] + t1 * dsb[1] + t2 * dsb[2]
    xtb = ajb * (-xt * ((aj > 0) / np.maximum(aj, 1e-300)))  # a_j² = ‖x_j‖² - (x_j·t)²
    utb = aib * (-ut * ((ai > 0) / np.maximum(ai, 1e-300)))  # a_i² = ‖u‖² - (u·t)²
    k_theta = bsb * sg * ((b > 0) / np.maximum(b, 1e-300))
    c_u = k_theta * nj2
    c_x = k_theta * ux
    c_r = rw * v["inv_ni"]
    ub = [c_r * r + aj * sb + c_u * uk - c_x * xk + utb * tk
          for r, sb, uk, xk, tk in ((ri0, sjb[0], u0, xj0, t0), (ri1, sjb[1], u1, xj1, t1), (ri2, sjb[2], u2, xj2, t2))]
    # per-edge sums: u × ū (direct part) and t̄ = b_s (s̄_j - s̄_i) + (x_j·t)‾ x_j + (u·t)‾ u
    np.multiply(u1, ub[2], out=acc[0]); acc[0] -= u2 * ub[1]  # noqa: E702
    np.multiply(u2, ub[0], out=acc[1]); acc[1] -= u0 * ub[2]  # noqa: E702
    np.multiply(u0, ub[1], out=acc[2]); acc[2] -= u1 * ub[0]  # noqa: E702
    for k, (dk, xk, uk) in enumerate(((dsb[0], xj0, u0), (dsb[1], xj1, u1), (dsb[2], xj2, u2))):
        np.multiply(bs, dk, out=acc[3 + k])
        acc[3 + k] += xtb * xk
        acc[3 + k] += utb * uk
    np.multiply(rw, v["sq"], out=acc[6])
    sums = np.add.reduceat(acc[:7], v["starts"], axis=1)
    out["cost"][rows] = sums[6]
    out["Jtr"][rows] = sums[0:3].T + np.einsum("eac,ea->ec", v["T"], sums[3:6].T)


def trrm_evaluate(R: np.ndarray, table: MatchTable, jacobian: np.ndarray | bool = False,
                  evaluate: np.ndarray | None = None, unit_theta: bool = False,
                  sq_out: np.ndarray | None = None, plain_ps: bool = False,
                  gradient: np.ndarray | bool = False) -> dict:
    """Per-edge TRRM cost Σ w ‖r‖² (eq:ROMerr), signed t and, for the edges where
    ``jacobian`` is true, JᵀJ and Jᵀr of the exact Jacobian (left perturbation); where
    only ``gradient`` is true, Jᵀr alone (reverse mode, JᵀJ left zero).

    ``evaluate`` (E,) bool: the edges to evaluate (default all; ``jacobian`` implies it).
    ``sq_out`` (M,): per-match ‖r‖² (validity-masked, without weights) of evaluated edges.
    ``plain_ps``: also return the unweighted Pˢ (E, 3, 3) (identification eigenvalues) and
    its null vector with the chirality sign, ``t_plain`` (= twoview.translation_directions).
    Per-edge results do not depend on which other edges are evaluated with them.
    """
    E = table.num_edges
    jac = np.broadcast_to(np.asarray(jacobian, dtype=bool), (E,))
    grad = np.broadcast_to(np.asarray(gradient, dtype=bool), (E,)) & ~jac
    ev = np.ones(E, dtype=bool) if evaluate is None else np.asarray(evaluate, dtype=bool) | jac | grad
    mode = np.where(jac, NORMAL, np.where(grad, GRADIENT, COST))
    out = {"cost": np.zeros(E), "t": np.zeros((E, 3))}
    if jac.any() or grad.any():
        out["JtJ"] = np.zeros((E, 3, 3))
        out["Jtr"] = np.zeros((E, 3))
    if plain_ps:
        out["ps"] = np.zeros((E, 6))
        out["t_plain"] = np.zeros((E, 3))
    data, w_all = table.data, table.weights
    # per group: one task on the contiguous slice when all its edges share a mode (the common
    # case), else one task per mode on gathered matches; mode -1: not evaluated
    code = np.where(ev, mode, -1)
    group_lo, group_hi = table.group_code_range(code)
    tasks = []  # (R, cnt, starts, d, w, mode, rows, sq, idx): idx = where to scatter a gathered sq
    for g, (e0, e1, m0, m1, cnt, starts) in enumerate(table.group_slices()):
        lo, hi = group_lo[g], group_hi[g]
        if hi < 0:
            continue
        whole = (R[e0:e1], cnt, starts, data[:, m0:m1], None if w_all is None else w_all[m0:m1])
        sq_view = None if sq_out is None else sq_out[m0:m1]
        modes = (NORMAL, GRADIENT, COST)
        if lo >= 0 and np.count_nonzero(code[e0:e1] == COST) * 2 >= e1 - e0:
            # mostly COST (an LM iteration where most edges test their last candidate): COST on
            # the whole slice without a gather, then the other modes on their edges, which
            # overwrite the same cost, t and ‖r‖² (the forward pass is shared) with their own
            tasks.append((*whole, COST, slice(e0, e1), sq_view, None))
            if lo == hi:
                continue
            modes = (NORMAL, GRADIENT)
        elif lo == hi:
            tasks.append((*whole, int(lo), slice(e0, e1), sq_view, None))
            continue
        for group_mode in modes:
            sel = np.flatnonzero(code[e0:e1] == group_mode)
            if sel.size == 0:
                continue
            cnt_sel = cnt[sel]
            starts_sel = np.concatenate([[0], np.cumsum(cnt_sel)[:-1]])
            within = np.arange(cnt_sel.sum()) - np.repeat(starts_sel, cnt_sel)
            idx = np.repeat(table.offsets[e0:e1][sel], cnt_sel) + within
            tasks.append((R[e0:e1][sel], cnt_sel, starts_sel, data[:, idx], None if w_all is None else w_all[idx],
                          group_mode, e0 + sel, None if sq_out is None else np.empty(idx.size), idx))
    for k0 in range(0, len(tasks), EIGEN_BATCH_GROUPS):
        batch_tasks = tasks[k0:k0 + EIGEN_BATCH_GROUPS]
        heads = [_lean_head(Rk, cnt, starts, d, w, unit_theta, plain_ps)
                 for Rk, cnt, starts, d, w, *_ in batch_tasks]
        sizes = np.cumsum([len(cnt) for _, cnt, *_ in batch_tasks])[:-1]
        lam, t, t_plain = _head_eigen(np.concatenate([h[2] for h in heads], axis=1))
        for task, head, lam_k, t_k, tp_k in zip(batch_tasks, heads, np.split(lam, sizes), np.split(t, sizes),
                                                np.split(t_plain, sizes)):
            Rk, cnt, starts, d, w, group_mode, rows, sq, idx = task
            _lean_group(Rk, cnt, starts, d, w, group_mode, unit_theta, out, rows, sq, plain_ps,
                        pre=(head, (lam_k, t_k, tp_k)))
            if idx is not None and sq is not None:
                sq_out[idx] = sq
    if plain_ps:
        p = out["ps"]
        out["ps"] = p[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(E, 3, 3)
    return out


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
    T = -_pinv_shifted(P, lam, t) @ dPt
    G = Lct + np.einsum("eak,eac->eck", L, T)  # J_k[c] = G_c · m_k
    GM = G @ M
    out["JtJ"] = GM @ np.swapaxes(G, 1, 2)
    out["Jtr"] = np.einsum("eck,ek->ec", G, y)
    return out


# ----------------------------------------------------------------------------- robust medians, Procrustes
def segment_median(values: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """twoview.segment_median (per-edge upper median, the element of rank ⌊m/2⌋) with one
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
        within = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
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
    """twoview.best_pure_rotation on a MatchTable (same Procrustes and Cauchy rounds)."""
    from rotonly_cli.geometry import so3

    R = so3.project_to_so3(bearing_cross_moment(table))
    for _ in range(robust_iterations):
        sq = rotated_bearing_sq(R, table)
        c2 = np.repeat((3.0 * 1.4826) ** 2 * segment_median(sq, table.offsets) + 1e-30, table.counts)
        R = so3.project_to_so3(bearing_cross_moment(table, 1.0 / (1.0 + sq / c2)))
    return R


def point_moments(batch: tv.EdgeBatch) -> tuple[np.ndarray, np.ndarray]:
    """Gⁱ = Σ X_i X_iᵀ and Gʲ of the z = 1 points per edge, (E, 3, 3) each
    (eq:case2IdentifyingMatrixBasic); the division by z is skipped when z is already 1."""
    E = batch.num_edges
    G = [np.empty((E, 3, 3)), np.empty((E, 3, 3))]
    pa, pb = np.triu_indices(3)
    for e0, e1 in _edge_groups(batch.counts, LEAN_CHUNK) if E else []:
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
