"""Per-match TRRM and λ_min(Pˢ) terms in forward mode: cost, JᵀJ and Jᵀr per edge, and the
per-match residuals and Jacobian columns that GRRM chains to the cameras.

Same mathematics as :func:`rotonly_cli.geometry.pairwise.trrm_residuals` and
:func:`~rotonly_cli.geometry.pairwise.epipolar_residuals` (the readable reference versions,
checked against finite differences in the tests), organised for speed: the exact Jacobian
is built column by column (one pass per rotation axis) over edge groups (kernels/soa.py);
the loop is over groups of edges, never over edges.
"""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.kernels.soa import (
    CHUNK_MATCHES,
    axpy,
    cross,
    dot,
    edge_chunks,
    pinv_shifted,
    rep,
    rotate,
    seg,
)


def _ps_from(theta, starts, w=None):
    if w is not None:  # Σ w θ θᵀ
        wt = tuple(w * v for v in theta)
        return _ps_pairs(wt, theta, starts)
    return _ps_pairs(theta, theta, starts)


def _ps_pairs(a, theta, starts):
    s00 = seg(a[0] * theta[0], starts)
    s01 = seg(a[0] * theta[1], starts)
    s02 = seg(a[0] * theta[2], starts)
    s11 = seg(a[1] * theta[1], starts)
    s12 = seg(a[1] * theta[2], starts)
    s22 = seg(a[2] * theta[2], starts)
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
            out[:, r, c] = seg(col, starts)
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
        Jtr[:, a] = seg(sum(ja * ra for ja, ra in zip(J_cols[a], r)), starts)
        for b in range(a, 3):
            v = seg(sum(ja * jb for ja, jb in zip(J_cols[a], J_cols[b])), starts)
            JtJ[:, a, b] = v
            JtJ[:, b, a] = v
    return JtJ, Jtr


def trrm_chunk_terms(Rg: np.ndarray, cnt: np.ndarray, starts: np.ndarray, xi, xj, with_jacobian: bool,
                wk: np.ndarray | None = None) -> dict:
    """TRRM terms of one edge group, per match: residual rows r (6 arrays: r_i in camera-j
    axes, then r_j), ‖θ‖, validity weight, t per edge and, with the Jacobian, the three
    forward-mode columns J_cols[c] (6 arrays) and d‖θ‖/dδ_c, for R_ij <- exp([δ]x) R_ij."""
    u = rotate(Rg, cnt, xi)
    theta = cross(u, xj)
    P = _ps_from(theta, starts, wk)
    lam, t = pg.smallest_eigenpair(P)
    t_m = tuple(rep(t[:, k], cnt) for k in range(3))
    xj_x_t = cross(xj, t_m)
    u_x_t = cross(u, t_m)
    # chirality sign (pairwise._chirality_sign_from)
    depth_i = dot(theta, xj_x_t)
    depth_j = dot(theta, u_x_t)
    vote = seg(((depth_i > 0) & (depth_j > 0)).astype(np.int64) - ((depth_i < 0) & (depth_j < 0)), starts)
    sign = np.where(vote < 0, -1.0, 1.0)
    if np.any(sign < 0):
        t = t * sign[:, None]
        sgn_m = rep(sign, cnt)
        t_m = tuple(sgn_m * v for v in t_m)
        xj_x_t = tuple(sgn_m * v for v in xj_x_t)
        u_x_t = tuple(sgn_m * v for v in u_x_t)
    a_j = np.sqrt(dot(xj_x_t, xj_x_t))
    a_i = np.sqrt(dot(u_x_t, u_x_t))
    b = np.sqrt(dot(theta, theta))
    s_j = axpy(a_j, u, b, t_m)
    s_i = axpy(a_i, xj, -b, t_m)
    n_xj = np.sqrt(dot(xj, xj))
    n_u = np.sqrt(dot(u, u))
    n_sj = np.sqrt(dot(s_j, s_j))
    n_si = np.sqrt(dot(s_i, s_i))
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
    xj_dot_u = dot(xj, u)
    u_dot_t = dot(u, t_m)
    theta_dot_t = dot(theta, t_m)
    T = -pinv_shifted(P, lam, t) @ _dPt(theta, theta_dot_t, u, xj, xj_dot_u, u_dot_t, t_m, starts, wk)
    inv_aj = np.where(a_j > 0, 1.0 / np.where(a_j > 0, a_j, 1.0), 0.0)
    inv_ai = np.where(a_i > 0, 1.0 / np.where(a_i > 0, a_i, 1.0), 0.0)
    inv_b = np.where(b > 0, 1.0 / np.where(b > 0, b, 1.0), 0.0)
    J_cols, db_cols = [], []
    for c in range(3):
        du = _du(c, u)
        dtheta = cross(du, xj)
        dt = tuple(rep(T[:, k, c], cnt) for k in range(3))
        da_j = dot(xj_x_t, cross(xj, dt)) * inv_aj
        db = dot(theta, dtheta) * inv_b
        d_uxt = cross(du, t_m)
        u_x_dt = cross(u, dt)
        da_i = dot(u_x_t, (d_uxt[0] + u_x_dt[0], d_uxt[1] + u_x_dt[1], d_uxt[2] + u_x_dt[2])) * inv_ai
        ds_j = tuple(da_j * u[k] + a_j * du[k] + db * t_m[k] + b * dt[k] for k in range(3))
        ds_i = tuple(da_i * xj[k] - db * t_m[k] - b * dt[k] for k in range(3))
        pj = dot(sj_hat, ds_j)
        pi = dot(si_hat, ds_i)
        col = tuple(w * (du[k] * inv_u - (ds_i[k] - si_hat[k] * pi) * inv_si) for k in range(3)) + \
            tuple(-w * (ds_j[k] - sj_hat[k] * pj) * inv_sj for k in range(3))
        J_cols.append(col)
        db_cols.append(db)
    out["J_cols"] = J_cols
    out["db"] = db_cols
    return out


def _outputs(E: int, with_jacobian: bool):
    """Zeroed per-edge cost (E,), t (E, 3) and, with the Jacobian, JᵀJ (E, 3, 3), Jᵀr (E, 3)."""
    return (np.zeros(E), np.zeros((E, 3)), np.zeros((E, 3, 3)) if with_jacobian else None,
            np.zeros((E, 3)) if with_jacobian else None)


def trrm_normal_equations(R: np.ndarray, batch: pg.EdgeBatch, with_jacobian: bool = True,
                          chunk: int = CHUNK_MATCHES) -> pg.ResidualEvaluation:
    """Per-edge TRRM cost (eq:ROMerr) and, optionally, JᵀJ and Jᵀr (exact Jacobian).

    With ``batch.weights`` w: Pˢ = Σ w θθᵀ and cost Σ w ‖r‖² (weights held fixed: one IRLS
    round of the robust TRRM in geometry/trrm.py).
    """
    cost, t_all, JtJ, Jtr = _outputs(batch.num_edges, with_jacobian)
    for e0, e1, _, _, cnt, starts, xi, xj, wk in edge_chunks(batch, chunk):
        terms = trrm_chunk_terms(R[e0:e1], cnt, starts, xi, xj, with_jacobian, wk)
        t_all[e0:e1] = terms["t"]
        r, J_cols = terms["r"], terms.get("J_cols")
        if wk is not None:
            root_w = np.sqrt(wk)
            r = tuple(root_w * v for v in r)
            if with_jacobian:
                J_cols = [tuple(root_w * v for v in col) for col in J_cols]
        cost[e0:e1] = seg(sum(v * v for v in r), starts)
        if with_jacobian:
            JtJ[e0:e1], Jtr[e0:e1] = _accumulate(J_cols, r, starts, e1 - e0)
    return pg.ResidualEvaluation(residuals=None, cost=cost, t=t_all, JtJ=JtJ, Jtr=Jtr)


def trrm_match_terms(R: np.ndarray, batch: pg.EdgeBatch, with_jacobian: bool = True,
                     chunk: int = CHUNK_MATCHES) -> dict:
    """Per-match TRRM terms for GRRM: ``r`` (M, 6) [r_i in camera-j axes, r_j], ``b`` (M,) = ‖θ‖,
    ``w`` (M,) validity, ``t`` (E, 3) and, with the Jacobian, ``J`` (M, 6, 3) = dr/dδ and
    ``db`` (M, 3) = d‖θ‖/dδ for the left perturbation of each edge's R_ij."""
    M = batch.x_i.shape[0]
    out = {"r": np.empty((M, 6)), "b": np.empty(M), "w": np.empty(M), "t": np.zeros((batch.num_edges, 3))}
    if with_jacobian:
        out["J"] = np.empty((M, 6, 3))
        out["db"] = np.empty((M, 3))
    for e0, e1, m0, m1, cnt, starts, xi, xj, wk in edge_chunks(batch, chunk):
        terms = trrm_chunk_terms(R[e0:e1], cnt, starts, xi, xj, with_jacobian, wk)
        out["t"][e0:e1] = terms["t"]
        out["r"][m0:m1] = np.stack(terms["r"], axis=1)
        out["b"][m0:m1] = terms["b"]
        out["w"][m0:m1] = terms["w"]
        if with_jacobian:
            for c in range(3):
                out["J"][m0:m1, :, c] = np.stack(terms["J_cols"][c], axis=1)
                out["db"][m0:m1, c] = terms["db"][c]
    return out


def epipolar_normal_equations(R: np.ndarray, batch: pg.EdgeBatch, with_jacobian: bool = True,
                              chunk: int = CHUNK_MATCHES) -> pg.ResidualEvaluation:
    """Per-edge λ_min(Pˢ) of bearing-normalised θ (pairwise.epipolar_residuals), JᵀJ, Jᵀr."""
    cost, t_all, JtJ, Jtr = _outputs(batch.num_edges, with_jacobian)
    for e0, e1, _, _, cnt, starts, xi, xj, wk in edge_chunks(batch, chunk):
        scale = 1.0 / (np.sqrt(dot(xi, xi)) * np.sqrt(dot(xj, xj)))
        u = rotate(R[e0:e1], cnt, xi)
        theta = tuple(scale * v for v in cross(u, xj))
        P = _ps_from(theta, starts, wk)
        lam, t = pg.smallest_eigenpair(P)
        t_all[e0:e1] = t
        t_m = tuple(rep(t[:, k], cnt) for k in range(3))
        e = dot(theta, t_m)
        cost[e0:e1] = seg(e * e if wk is None else wk * e * e, starts)
        if not with_jacobian:
            continue
        # A = scale (u x_j^T - (x_j·u) I); dPt as in _dPt with the scaled A
        xj_dot_u = dot(xj, u)
        u_dot_t = dot(u, t_m)
        dPt = _dPt(theta, e * scale, u, xj, xj_dot_u, u_dot_t * scale, tuple(scale * v for v in t_m), starts, wk)
        T = -pinv_shifted(P, lam, t) @ dPt
        J_cols = []
        for c in range(3):
            At_t_c = scale * (xj[c] * u_dot_t - xj_dot_u * t_m[c])
            dt = tuple(rep(T[:, k, c], cnt) for k in range(3))
            J_cols.append((At_t_c + dot(theta, dt),))
        if wk is not None:
            root_w = np.sqrt(wk)
            J_cols = [(root_w * col[0],) for col in J_cols]
            e = root_w * e
        JtJ[e0:e1], Jtr[e0:e1] = _accumulate(J_cols, (e,), starts, e1 - e0)
    return pg.ResidualEvaluation(residuals=None, cost=cost, t=t_all, JtJ=JtJ, Jtr=Jtr)
