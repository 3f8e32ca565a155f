"""Leave-one-out test of a rotation graph's edges: does each pair's own data agree with the
relative rotation that the *other* pairs imply?

GRRM (eq:GRRMRes2) takes every match of every pair with the pair's translation free, so a
pair whose matches are consistently wrong (repeated structure that fits the pair's own
epipolar geometry) pulls the global rotations towards itself. Where the pair is weakly
tied (few matches across a thin part of the graph) it pulls them far, and under the bent
solution its own matches fit well: its residual under the global rotations cannot tell it
apart (docs/tuning.md "Refutation by the other pairs"). Left out, it would misfit. That is
the externally studentised residual of regression diagnostics, here for rotation graphs (docs/algorithms.md §2.4).

The exact test re-solves GRRM once per edge. Its linearisation costs one factorisation:
about the current rotations, each edge e = (i, j) is a 3-vector measurement of the
relative rotation (left perturbation in camera j's axes, δ_e = δ_j - R_ij δ_i, the chain
of GRRM's normal equations, grrm/problem.py) with the information W_e = J_eᵀ J_e of its own epipolar residuals
(pairwise.epipolar_residuals: t_ij profiled out, eq:minlambda). With H = Σ A_eᵀ W_e A_e,
S = H⁻¹ (one view held: the gauge), P_e = A_e S A_eᵀ and u_e = A_e S b, the
Sherman-Morrison-Woodbury identity gives the relative rotation the others imply without
refitting: A_e δ_(-e) = (I - P_e W_e)⁻¹ (u_e - P_e W_e r_e). It is applied as a *change*
to the current (GRRM) relative rotation, so only the averaging's sensitivity is linearised.

The statistic is scale-free: the median epipolar residual of the edge's matches under the
left-out relative rotation, over the median under its own (TRRM) rotation. A bridge (no
cycle through it) has nothing else to disagree with: NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3

#: P_e W_e's eigenvalues are the edge's leverages, in [0, 1]: (I - P_e W_e) with a singular
#: value below this leaves the edge (nearly) all the information on its relative rotation,
#: as a bridge has; no leave-one-out rotation
_MIN_FREEDOM = 1e-6


@dataclass
class LeaveOneOut:
    """Per edge (E,): ``fit_ratio`` = median epipolar residual of its matches under the
    relative rotation the other edges imply over the median under its own rotation (NaN
    where the others imply nothing: bridges, skipped edges); ``change_deg``: how far the
    current relative rotation would move without the edge; ``R_j_from_i``: that rotation."""

    fit_ratio: np.ndarray
    change_deg: np.ndarray
    R_j_from_i: np.ndarray


def left_out_changes(R_ij: np.ndarray, edge_views: np.ndarray, r: np.ndarray, W: np.ndarray, n: int,
                     fixed_view: int = 0, skip: np.ndarray | None = None) -> np.ndarray:
    """(E, 3): how each edge's relative rotation moves (left perturbation, camera j's axes)
    when the edge is left out of the linearised averaging about the rotations whose relative
    rotations are ``R_ij`` (E, 3, 3), the edges measuring ``r`` (E, 3) with information ``W``
    (E, 3, 3), ``n`` views, one held. NaN for ``skip``ped edges and for those (I - P_e W_e)
    leaves undetermined (bridges).

    Block by block: A_e has I at view j and -R_ij at view i, so H's blocks and P_e = A_e S A_eᵀ
    = S_jj - S_ji R_ijᵀ - R_ij S_ij + R_ij S_ii R_ijᵀ take O(E) 3 x 3 products; only S = H⁻¹
    (3n x 3n) is dense."""
    edge_views = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
    i, j = edge_views[:, 0], edge_views[:, 1]
    Rt = np.transpose(R_ij, (0, 2, 1))
    H = np.zeros((n, n, 3, 3))
    np.add.at(H, (j, j), W)
    np.add.at(H, (i, i), Rt @ W @ R_ij)
    np.add.at(H, (j, i), -W @ R_ij)
    np.add.at(H, (i, j), -Rt @ W)
    b = np.zeros((n, 3))
    Wr = np.einsum("eab,eb->ea", W, r)
    np.add.at(b, j, Wr)
    np.add.at(b, i, -np.einsum("eba,eb->ea", R_ij, Wr))
    free = np.ones(3 * n, dtype=bool)
    free[3 * fixed_view:3 * fixed_view + 3] = False
    H = H.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)[np.ix_(free, free)]
    S = np.zeros((3 * n, 3 * n))
    try:
        S[np.ix_(free, free)] = np.linalg.inv(H)
    except np.linalg.LinAlgError:  # pairs without information on some rotation: nothing to test
        return np.full((len(r), 3), np.nan)
    delta = (S @ b.ravel()).reshape(n, 3)
    S = S.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)  # S[a, b] = the (a, b) 3 x 3 block
    u = delta[j] - np.einsum("eab,eb->ea", R_ij, delta[i])
    P = S[j, j] - S[j, i] @ Rt - R_ij @ S[i, j] + R_ij @ S[i, i] @ Rt
    PW = P @ W
    lhs = np.eye(3) - PW
    tested = np.ones(len(r), dtype=bool) if skip is None else ~np.asarray(skip, dtype=bool)
    tested &= np.linalg.svd(lhs, compute_uv=False)[:, -1] > _MIN_FREEDOM
    change = np.full((len(r), 3), np.nan)
    if tested.any():
        rhs = u[tested] - np.einsum("eab,eb->ea", PW[tested], r[tested])
        change[tested] = np.linalg.solve(lhs[tested], rhs[:, :, None])[:, :, 0] - u[tested]
    return change


def leave_one_out(R_cam_from_world: np.ndarray, edge_views: np.ndarray, R_j_from_i: np.ndarray,
                  batch: pg.EdgeBatch, skip: np.ndarray | None = None, fixed_view: int = 0) -> LeaveOneOut:
    """The linearised leave-one-out test (module docstring) of every edge.

    ``R_cam_from_world`` (n, 3, 3): the global rotations (GRRM's); ``edge_views`` (E, 2):
    each edge's (i, j) rows; ``R_j_from_i`` (E, 3, 3): each edge's own relative rotation
    (TRRM's), estimated from ``batch``'s matches; ``skip`` (E,) bool: edges not tested (NaN),
    bridges for instance, which still count for the others. One view is held
    (``fixed_view``); the edges must tie every view together."""
    R = np.asarray(R_cam_from_world, dtype=float)
    edge_views = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
    R_e = pg.as_rotations(R_j_from_i, batch=len(edge_views))
    own = pg.epipolar_residuals(R_e, batch, with_jacobian=True)
    own_median = pg.segment_median(np.abs(own.residuals[:, 0]), batch)
    R_ij = R[edge_views[:, 1]] @ np.transpose(R[edge_views[:, 0]], (0, 2, 1))
    r = so3.log(R_e @ np.transpose(R_ij, (0, 2, 1)))  # R_e = exp(r) R_ij
    change = left_out_changes(R_ij, edge_views, r, own.JtJ, len(R), fixed_view, skip)
    tested = np.isfinite(change).all(axis=1)
    R_out = so3.exp(np.where(tested[:, None], change, 0.0)) @ R_ij
    left_out_median = pg.segment_median(np.abs(pg.epipolar_residuals(R_out, batch).residuals[:, 0]), batch)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(tested, left_out_median / own_median, np.nan)
    return LeaveOneOut(fit_ratio=ratio, change_deg=np.degrees(np.linalg.norm(change, axis=1)), R_j_from_i=R_out)
