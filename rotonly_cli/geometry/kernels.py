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
                wk: np.ndarray | None = None) -> dict:
    """TRRM terms of one edge group, per match: residual rows r (6 arrays: r_i in camera-j
    axes, then r_j), ‖θ‖, validity weight, t per edge and, with the Jacobian, the three
    forward-mode columns J_cols[c] (6 arrays) and d‖θ‖/dδ_c, for R_ij <- exp([δ]x) R_ij."""
    u = _rotate(Rg, cnt, xi)
    theta = _cross(u, xj)
    P = _ps_from(theta, starts, wk)
    lam, t = tv.smallest_eigenpair(P)
    t_m = tuple(_rep(t[:, k], cnt) for k in range(3))
    xj_x_t = _cross(xj, t_m)
    u_x_t = _cross(u, t_m)
    # chirality sign (twoview._chirality_sign_from)
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
    T = -_pinv_shifted(P, lam, t) @ _dPt(theta, theta_dot_t, u, xj, xj_dot_u, u_dot_t, t_m, starts, wk)
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
