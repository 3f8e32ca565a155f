"""GRRM with every edge's t_ij held fixed: a diagnostic, not part of rotonly.

The paper's GRRM gives each edge its closed-form t_ij(R_ij), the null vector of its Pˢ. Holding
t_ij at given directions instead (the ground truth: an oracle; LiGT's; averaged centres')
shows how much of GRRM's rotation error the per-edge translations carry
(probe_grrm_structure.py, table ``translations``).

Only one thing changes: the per-match TRRM terms (``fixed_translation_terms``: t given,
unit length and sign included, no chirality flip, dt/dδ = 0). ``GRRMSystem.chunk_terms`` is
the seam; :func:`optimize_with_translations` runs rotonly's own GRRM with a system that
uses it, without the λ_min phase and the translation weights (they only serve Pˢ).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace

import numpy as np

from rotonly_cli.geometry.grrm import GRRMOptions, GRRMSystem, solve
from rotonly_cli.geometry.kernels.forward import _du
from rotonly_cli.geometry.kernels.soa import axpy, cross, dot, rep, rotate


def fixed_translation_terms(Rg: np.ndarray, cnt: np.ndarray, starts: np.ndarray, xi, xj, with_jacobian: bool,
                            t: np.ndarray) -> dict:
    """kernels.trrm_chunk_terms with each edge's unit t_ij (camera j) given: the residual of
    eq:PA3bearing at a known translation, and its Jacobian with dt/dδ = 0."""
    u = rotate(Rg, cnt, xi)
    theta = cross(u, xj)
    t_m = tuple(rep(t[:, k], cnt) for k in range(3))
    xj_x_t = cross(xj, t_m)
    u_x_t = cross(u, t_m)
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
    inv_ai = np.where(a_i > 0, 1.0 / np.where(a_i > 0, a_i, 1.0), 0.0)
    inv_b = np.where(b > 0, 1.0 / np.where(b > 0, b, 1.0), 0.0)
    J_cols, db_cols = [], []
    for c in range(3):
        du = _du(c, u)
        dtheta = cross(du, xj)
        db = dot(theta, dtheta) * inv_b
        d_uxt = cross(du, t_m)
        da_i = dot(u_x_t, d_uxt) * inv_ai
        ds_j = tuple(a_j * du[k] + db * t_m[k] for k in range(3))  # da_j = 0: x_j and t are fixed
        ds_i = tuple(da_i * xj[k] - db * t_m[k] for k in range(3))
        pj = dot(sj_hat, ds_j)
        pi = dot(si_hat, ds_i)
        col = tuple(w * (du[k] * inv_u - (ds_i[k] - si_hat[k] * pi) * inv_si) for k in range(3)) + \
            tuple(-w * (ds_j[k] - sj_hat[k] * pj) * inv_sj for k in range(3))
        J_cols.append(col)
        db_cols.append(db)
    out["J_cols"] = J_cols
    out["db"] = db_cols
    return out


def unit_translations(translations, num_edges: int) -> np.ndarray:
    """(E, 3) unit t_ij; ValueError for another shape or a zero / non-finite row."""
    t = np.asarray(translations, dtype=float)
    if t.shape != (num_edges, 3):
        raise ValueError(f"translations: expected shape ({num_edges}, 3), got {t.shape}")
    norm = np.linalg.norm(t, axis=1)
    if not np.all(np.isfinite(norm) & (norm > 0)):
        raise ValueError("translations: every edge needs a finite, non-zero t_ij")
    return t / norm[:, None]


def fixed_translation_system(translations: np.ndarray) -> type[GRRMSystem]:
    """A GRRMSystem whose edges use ``translations`` (E, 3), unit, instead of Pˢ's null vectors."""

    class FixedTranslationSystem(GRRMSystem):
        def chunk_terms(self, R_ij, edges, cnt, starts, xi, xj, with_jacobian, wk):
            return fixed_translation_terms(R_ij, cnt, starts, xi, xj, with_jacobian, translations[edges])

    return FixedTranslationSystem


@contextmanager
def _system(translations: np.ndarray):
    original = solve.GRRMSystem
    solve.GRRMSystem = fixed_translation_system(translations)
    try:
        yield
    finally:
        solve.GRRMSystem = original


def optimize_with_translations(R_cam_from_world, edge_views, batch, obs_ids, translations, fixed_view: int = 0,
                               options: GRRMOptions = GRRMOptions()):
    """rotonly's GRRM (grrm.optimize_global_rotations) with each edge's t_ij held at
    ``translations`` (E, 3; camera j, x_j ~ R_ij x_i + t_ij; any positive length)."""
    t = unit_translations(translations, batch.num_edges)
    options = replace(options, epipolar_max_iterations=0, robust_translation=False)
    with _system(t):
        return solve.optimize_global_rotations(R_cam_from_world, edge_views, batch, obs_ids, fixed_view, options)


def residuals_with_translations(R_cam_from_world, edge_views, batch, obs_ids, translations,
                                with_jacobian: bool = False, residual: str = "bearing"):
    """grrm.grrm_residuals with each edge's t_ij held at ``translations``."""
    t = unit_translations(translations, batch.num_edges)
    with _system(t):
        return solve.grrm_residuals(R_cam_from_world, edge_views, batch, obs_ids, with_jacobian, residual)


def optimize_graph_with_translations(graph, normalized: dict, R_cam_from_world: np.ndarray,
                                     translations: dict[int, np.ndarray]) -> np.ndarray:
    """stages.optimize.optimize_graph's rotations with t_ij held per graph edge index (every
    edge GRRM takes must have one)."""
    from rotonly_cli.stages.optimize import grrm_inputs

    R_out = np.array(R_cam_from_world, dtype=float, copy=True)
    inputs = grrm_inputs(graph, normalized, R_out)
    rows = [graph.view_ids().index(v) for v in inputs.views]
    with np.errstate(all="ignore"):
        result = optimize_with_translations(R_out[rows], inputs.edge_views, inputs.batch, inputs.obs_ids,
                                            np.stack([translations[k] for k in inputs.edges]))
    R_out[rows] = result.R_cam_from_world
    return R_out
