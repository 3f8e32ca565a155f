"""Robust rotation averaging (Chatterjee & Govindu L1RA + IRLS), algorithms.md §2.

Pure numpy/scipy. Model: ``R_j_from_i ≈ R_j R_iᵀ`` with ``R_k = R_cam_from_world``.

1. Start: maximum spanning tree of the view graph on the edge weights (COLMAP/GLOMAP use
   ``num_matches``; algorithms.md §2.1 step 1), rotations chained from ``fixed_view``.
2. Tangent residual per edge ``Δr_ij = Log(R_jᵀ R_ij R_i)`` and the linearised update
   ``R_k ← R_k Exp(Δω_k)``, ``Δr_ij ≈ Δω_j − Δω_i`` (§2.1 steps 2–3). The fixed view's
   columns are dropped. The incidence structure is the same for the three tangent axes, so
   ``A = incidence ⊗ I₃`` and every normal matrix is the (weighted) graph Laplacian applied
   to a (n−1, 3) right-hand side: one sparse factorisation serves all three axes.
3. L1RA (§2.1 step 4): ``min ‖AΔω − Δr‖₁`` by ADMM (Boyd et al. 2011, least absolute
   deviations; Theia's/COLMAP's ``L1Solver``). ``AᵀA`` is factorised once (SuperLU) and
   reused for all L1 steps; the ADMM iteration cap starts at ``admm_initial_iterations``
   and doubles each L1 step up to ``admm_max_iterations`` (COLMAP: 10 → 100).
4. IRLS (§2.1 step 5) with Geman–McClure ``w = σ²/(e²+σ²)²`` (σ = 5°, ICCV 2013) or ℓ½
   ``w = e^{−3/2}`` (HALF_NORM, TPAMI 2018, the seed/ROBA setting), multiplied by the
   normalised edge weights; ``(AᵀWA) Δω = AᵀWΔr`` solved with a sparse LU. With
   ``irls_sigma_residual_factor`` σ is measured instead: that many robust sigmas of the edge
   residuals at the L1 solution, at most the fixed σ (:func:`irls_sigma_deg`).
5. Per-edge residual angle after convergence; edges above ``max_inlier_residual_deg`` are
   flagged as outliers (they keep a small IRLS weight but are reported).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.geometry import so3
from rotonly_cli.options import AveragingOptions, RobustWeight

if TYPE_CHECKING:
    import scipy.sparse as sp

__all__ = ["RobustWeight", "AveragingOptions", "AveragingResult", "average_rotations",
           "spanning_tree_rotations", "edge_residuals", "irls_sigma_deg"]


@dataclass
class AveragingResult:
    R_cam_from_world: np.ndarray  # (n, 3, 3); NaN for views not connected to fixed_view
    registered: np.ndarray  # (n,) bool: in the connected component of fixed_view
    edge_residual_deg: np.ndarray  # (E,) angle of R_jᵀ R_ij R_i; NaN for unused edges
    inlier_mask: np.ndarray  # (E,) residual ≤ max_inlier_residual_deg
    l1_iterations: int
    irls_iterations: int
    irls_converged: bool
    irls_sigma_deg: float = float("nan")  # the Geman-McClure σ the IRLS used (irls_sigma_deg)

    @property
    def iterations(self) -> int:
        return self.l1_iterations + self.irls_iterations


def edge_residuals(R_cam_from_world: np.ndarray, edges_i: np.ndarray, edges_j: np.ndarray,
                   R_j_from_i: np.ndarray) -> np.ndarray:
    """Tangent residuals ``Log(R_jᵀ R_ij R_i)`` (E, 3) in radians."""
    R = R_cam_from_world
    return so3.log(np.transpose(R[edges_j], (0, 2, 1)) @ R_j_from_i @ R[edges_i])


def spanning_tree_rotations(num_views: int, edges_i: np.ndarray, edges_j: np.ndarray,
                            R_j_from_i: np.ndarray, weights: np.ndarray, fixed_view: int) -> np.ndarray:
    """Chain rotations along the maximum spanning tree from ``fixed_view`` (R = I there).

    Views not reached get NaN. Parallel edges: the heaviest of a pair is used.
    """
    import scipy.sparse as sp  # lazily (~0.3 s): `rotonly run` reports bad input before it
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    low, high = np.minimum(edges_i, edges_j), np.maximum(edges_i, edges_j)
    order = np.lexsort((-weights, high, low))  # heaviest first inside each pair
    first = np.ones(order.size, dtype=bool)
    first[1:] = (low[order][1:] != low[order][:-1]) | (high[order][1:] != high[order][:-1])
    best = order[first]
    # costs must be positive (scipy drops explicit zeros): max weight -> cost 1
    cost = weights[best].max() - weights[best] + 1.0
    graph = sp.coo_matrix((cost, (low[best], high[best])), shape=(num_views, num_views)).tocsr()
    tree = minimum_spanning_tree(graph)
    bfs_order, parent = breadth_first_order(tree, fixed_view, directed=False, return_predecessors=True)
    pair_key = low[best] * num_views + high[best]
    key_order = np.argsort(pair_key)
    R = np.full((num_views, 3, 3), np.nan)
    R[fixed_view] = np.eye(3)
    for child in bfs_order[1:]:  # one step per view (not per edge or observation)
        par = parent[child]
        key = min(par, child) * num_views + max(par, child)
        edge = best[key_order[np.searchsorted(pair_key, key, sorter=key_order)]]
        # R_child = R_child_from_par R_par; an edge stored as (child -> par) is inverted
        R_child_from_par = R_j_from_i[edge] if edges_i[edge] == par else R_j_from_i[edge].T
        R[child] = R_child_from_par @ R[par]
    return R


def _incidence(edges_i: np.ndarray, edges_j: np.ndarray, column_of_view: np.ndarray, num_free: int
               ) -> sp.csr_matrix:
    """Scalar incidence (E × num_free): −1 at i, +1 at j, the fixed view's column dropped."""
    import scipy.sparse as sp

    num_edges = edges_i.size
    rows = np.concatenate([np.arange(num_edges), np.arange(num_edges)])
    cols = np.concatenate([column_of_view[edges_i], column_of_view[edges_j]])
    vals = np.concatenate([-np.ones(num_edges), np.ones(num_edges)])
    keep = cols >= 0
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(num_edges, num_free))


def _frobenius(x: np.ndarray) -> float:
    # einsum, not np.linalg.norm: the BLAS dot behind norm was 100x slower here when
    # OpenBLAS threads compete for 2 cores (measured 2 ms per 33k-element norm)
    return float(np.sqrt(np.einsum("ij,ij->", x, x)))


def _l1_admm(A: sp.csr_matrix, AtA_lu, b: np.ndarray, max_iterations: int,
             options: AveragingOptions) -> np.ndarray:
    """ADMM for ``min_x ‖A x − b‖₁`` column-wise (b: (E, 3)); returns x (num_free, 3)."""
    rho = options.admm_rho
    z = np.zeros_like(b)
    u = np.zeros_like(b)
    x = np.zeros((A.shape[1], b.shape[1]))
    sqrt_size_primal = np.sqrt(b.size)
    sqrt_size_dual = np.sqrt(x.size)
    for _ in range(max_iterations):
        x = AtA_lu.solve(A.T @ (b + z - u))
        Ax = A @ x
        z_old = z
        v = Ax - b + u
        z = np.sign(v) * np.maximum(np.abs(v) - 1.0 / rho, 0.0)
        u = u + Ax - z - b
        primal = _frobenius(Ax - z - b)
        dual = rho * _frobenius(A.T @ (z - z_old))
        # Boyd et al. §3.3.1 stopping rule (absolute + relative tolerances)
        abs_tol, rel_tol = options.admm_absolute_tolerance, options.admm_relative_tolerance
        eps_primal = sqrt_size_primal * abs_tol + rel_tol * max(_frobenius(Ax), _frobenius(z), _frobenius(b))
        eps_dual = sqrt_size_dual * abs_tol + rel_tol * rho * _frobenius(A.T @ u)
        if primal < eps_primal and dual < eps_dual:
            break
    return x


def _average_step(step: np.ndarray) -> float:
    """Theia/COLMAP ``ComputeAverageStepSize``: mean over free views of ‖Δω_k‖ (rad)."""
    return float(np.linalg.norm(step, axis=1).mean()) if step.size else 0.0


def _irls_weights(residual_norm: np.ndarray, options: AveragingOptions, sigma_deg: float) -> np.ndarray:
    if options.weight_type == RobustWeight.GEMAN_MCCLURE:
        sigma = np.radians(sigma_deg)
        # COLMAP's σ²/(e²+σ²)², rescaled by σ² so weights are ~1 for inliers
        return (sigma**2 / (residual_norm**2 + sigma**2)) ** 2
    if options.weight_type == RobustWeight.HALF_NORM:
        e = np.maximum(residual_norm, np.radians(options.half_norm_min_residual_deg))
        return e ** -1.5
    return np.ones_like(residual_norm)


def irls_sigma_deg(residual_rad: np.ndarray, options: AveragingOptions) -> float:
    """The IRLS loss scale (deg): ``irls_loss_parameter_sigma_deg``, or with
    ``irls_sigma_residual_factor`` that many robust sigmas (1.4826 x the median) of the edge
    residuals at the L1 solution, within [``irls_min_sigma_deg``, ``irls_loss_parameter_sigma_deg``]."""
    if options.irls_sigma_residual_factor is None or not residual_rad.size:
        return options.irls_loss_parameter_sigma_deg
    scale = options.irls_sigma_residual_factor * 1.4826 * float(np.degrees(np.median(residual_rad)))
    return float(np.clip(scale, options.irls_min_sigma_deg, options.irls_loss_parameter_sigma_deg))


def average_rotations(num_views: int, edges_i: np.ndarray, edges_j: np.ndarray, R_j_from_i: np.ndarray,
                      weights: np.ndarray | None = None, fixed_view: int = 0,
                      options: AveragingOptions | None = None) -> AveragingResult:
    """Global rotations ``R_cam_from_world`` from relative rotations ``R_j_from_i = R_j R_iᵀ``.

    Args:
        num_views: n.
        edges_i, edges_j: (E,) view indices of each edge.
        R_j_from_i: (E, 3, 3) relative rotations.
        weights: (E,) edge quality (e.g. inlier counts) for the spanning tree and as IRLS
            multipliers; default all 1.
        fixed_view: gauge view, R = I.
    """
    options = options or AveragingOptions()
    options.validate()
    edges_i = np.asarray(edges_i, dtype=np.int64)
    edges_j = np.asarray(edges_j, dtype=np.int64)
    R_j_from_i = np.asarray(R_j_from_i, dtype=float)
    num_edges = edges_i.size
    if edges_j.shape != (num_edges,) or R_j_from_i.shape != (num_edges, 3, 3):
        raise InputError("edges_i, edges_j (E,) and R_j_from_i (E, 3, 3) disagree", field="R_j_from_i")
    if not np.all(np.isfinite(R_j_from_i)):
        raise InputError("non-finite relative rotation", field="R_j_from_i")
    weights = np.ones(num_edges) if weights is None else np.asarray(weights, dtype=float)
    if weights.shape != (num_edges,) or np.any(~np.isfinite(weights)) or np.any(weights <= 0):
        raise InputError("weights must be (E,) positive and finite", field="weights")
    if num_edges and (min(edges_i.min(), edges_j.min()) < 0 or max(edges_i.max(), edges_j.max()) >= num_views):
        raise InputError("edge view index out of range", field="edges")
    if np.any(edges_i == edges_j):
        raise InputError("self-loop edge (i == j)", field="edges")
    if not 0 <= fixed_view < num_views:
        raise InputError("fixed_view out of range", field="fixed_view")

    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    graph = sp.coo_matrix((np.ones(num_edges), (edges_i, edges_j)), shape=(num_views, num_views))
    _, component = connected_components(graph, directed=False)
    registered = component == component[fixed_view]
    if registered.sum() < 2:
        raise AlgorithmError(f"rotation averaging: fixed view {fixed_view} has no edges")
    used = registered[edges_i] & registered[edges_j]
    e_i, e_j, R_ij = edges_i[used], edges_j[used], R_j_from_i[used]
    edge_weight = weights[used] / weights[used].mean()

    R = spanning_tree_rotations(num_views, e_i, e_j, R_ij, edge_weight, fixed_view)
    free_views = np.flatnonzero(registered & (np.arange(num_views) != fixed_view))
    column_of_view = np.full(num_views, -1, dtype=np.int64)
    column_of_view[free_views] = np.arange(free_views.size)
    A = _incidence(e_i, e_j, column_of_view, free_views.size)

    def apply_step(step: np.ndarray) -> None:
        R[free_views] = R[free_views] @ so3.exp(step)

    l1_iterations = 0
    if not options.skip_l1 and options.max_num_l1_iterations > 0:
        AtA_lu = splu((A.T @ A).tocsc())  # the graph Laplacian, factorised once
        admm_iterations = options.admm_initial_iterations
        for _ in range(options.max_num_l1_iterations):
            l1_iterations += 1
            step = _l1_admm(A, AtA_lu, edge_residuals(R, e_i, e_j, R_ij), admm_iterations, options)
            apply_step(step)
            admm_iterations = min(2 * admm_iterations, options.admm_max_iterations)
            if _average_step(step) < options.l1_step_convergence_threshold:
                break

    irls_iterations, converged = 0, options.max_num_irls_iterations == 0
    residual = edge_residuals(R, e_i, e_j, R_ij)  # at the L1 solution: the IRLS scale is measured on it
    sigma_deg = irls_sigma_deg(np.linalg.norm(residual, axis=1), options)
    ridge = sp.identity(free_views.size, format="csc") * options.ridge_regularization
    for _ in range(options.max_num_irls_iterations):
        irls_iterations += 1
        w = _irls_weights(np.linalg.norm(residual, axis=1), options, sigma_deg) * edge_weight
        AtW = A.T.multiply(w[None, :]).tocsr()
        step = splu((AtW @ A).tocsc() + ridge).solve(AtW @ residual)
        apply_step(step)
        if _average_step(step) < options.irls_step_convergence_threshold:
            converged = True
            break
        residual = edge_residuals(R, e_i, e_j, R_ij)

    residual_deg = np.full(num_edges, np.nan)
    residual_deg[used] = np.degrees(np.linalg.norm(edge_residuals(R, e_i, e_j, R_ij), axis=1))
    inlier = np.zeros(num_edges, dtype=bool)
    inlier[used] = residual_deg[used] <= options.max_inlier_residual_deg
    R[~registered] = np.nan
    return AveragingResult(R, registered, residual_deg, inlier, l1_iterations, irls_iterations, converged, sigma_deg)
