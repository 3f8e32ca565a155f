"""GRRM's optimisation (paper Alg. 4): Levenberg-Marquardt on the 3n rotation parameters with
one view fixed, after an optional λ_min(Pˢ) phase."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.grrm.problem import GRRMSystem, chain_matrix
from rotonly_cli.geometry.robust import robust_rho
from rotonly_cli.options import GRRMOptions

log = logging.getLogger("rotonly.grrm")


@dataclass
@dataclass
class GRRMResult:
    R_cam_from_world: np.ndarray  # (n, 3, 3)
    initial_cost: float  # eq:GRRMerror (robustified if a loss is used) at the start
    cost: float  # ... at the end
    iterations: int
    converged: bool
    history: list[dict] = field(default_factory=list)
    num_observations: int = 0
    loss_scale: float = 0.0
    processes: int = 1  #: processes the evaluation ran in (GRRMSystem.parallel)
    #: where the kept descent started: "input", or "lambda_min" (the λ_min phase's end; GRRM
    #: then also descended from the input start, and kept the lower final cost)
    start: str = "input"
    descents: int = 1  #: LM descents run (2 when the λ_min phase's start was taken)


def validate_inputs(R_cam_from_world, edge_views, batch: pg.EdgeBatch | pg.ObservedMatches,
                    obs_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R = pg.as_rotations(R_cam_from_world, "R_cam_from_world").reshape(-1, 3, 3).astype(float)
    n = R.shape[0]
    edge_views = np.asarray(edge_views)
    if edge_views.ndim != 2 or edge_views.shape[1] != 2 or edge_views.shape[0] != batch.num_edges:
        raise ValueError(f"edge_views: expected shape ({batch.num_edges}, 2), got {edge_views.shape}")
    if not np.issubdtype(edge_views.dtype, np.integer):
        raise ValueError("edge_views: must be integer view indices")
    if edge_views.size and (edge_views.min() < 0 or edge_views.max() >= n
                            or np.any(edge_views[:, 0] == edge_views[:, 1])):
        raise ValueError(f"edge_views: view indices must be distinct and in [0, {n})")
    obs_ids = np.asarray(obs_ids)
    M = pg.num_matches(batch)
    if obs_ids.shape != (M, 2) or not np.issubdtype(obs_ids.dtype, np.integer):
        raise ValueError(f"obs_ids: expected an integer array of shape ({M}, 2), got {obs_ids.shape}")
    # (M, 2): int32 from stages.optimize where the keypoints allow (8 bytes per match), kept as given
    if obs_ids.dtype not in (np.int32, np.int64):
        obs_ids = obs_ids.astype(np.int64)
    return R, edge_views.astype(np.int64, copy=False), obs_ids


def _block_diag(blocks: np.ndarray) -> sp.csr_matrix:
    E = len(blocks)
    rows = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, :, None], (E, 3, 3)).ravel()
    cols = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * E, 3 * E))


def _solve_damped(JtJ, grad, mu, remainder=None):
    """LM step -(JᵀJ + μ diag(JᵀJ))⁻¹ g; JᵀJ dense (ndarray) or sparse; None if singular.

    With ``remainder`` (the exact Hessian's negative part, see GRRMSystem.linearize), first
    with JᵀJ - remainder in place of JᵀJ if that damped system is positive definite (dense:
    Cholesky; sparse: positive curvature along the step), else as without it."""
    diag = JtJ.diagonal()
    diag = np.where(diag > 0, diag, 1.0)
    if remainder is not None:
        try:
            if isinstance(JtJ, np.ndarray):
                delta = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(JtJ - remainder + np.diag(mu * diag)), grad)
            else:
                A = (JtJ - remainder + sp.diags(mu * diag)).tocsc()
                delta = -spla.spsolve(A, grad)
                if not float(delta @ (A @ delta)) > 0:
                    delta = None
            if delta is not None and np.all(np.isfinite(delta)):
                return delta
        except (RuntimeError, np.linalg.LinAlgError):
            pass
    try:
        if isinstance(JtJ, np.ndarray):
            delta = -np.linalg.solve(JtJ + np.diag(mu * diag), grad)
        else:
            delta = -spla.spsolve((JtJ + sp.diags(mu * diag)).tocsc(), grad)
    except (RuntimeError, np.linalg.LinAlgError):
        return None
    return delta if np.all(np.isfinite(delta)) else None


def _epipolar_terms(R_ij: np.ndarray, batch: pg.EdgeBatch | pg.ObservedMatches) -> pg.ResidualEvaluation:
    """kernels.epipolar_normal_equations of every edge; of ObservedMatches group by group of
    edges (per-edge numbers: the same)."""
    if isinstance(batch, pg.EdgeBatch):
        return kernels.epipolar_normal_equations(R_ij, batch)
    groups = [kernels.epipolar_normal_equations(R_ij[e0:e1], sub) for e0, e1, sub in pg.edge_group_batches(batch)]
    return pg.ResidualEvaluation(residuals=None, cost=np.concatenate([g.cost for g in groups]),
                                 t=np.concatenate([g.t for g in groups]), JtJ=np.concatenate([g.JtJ for g in groups]),
                                 Jtr=np.concatenate([g.Jtr for g in groups]))


def epipolar_phase(R: np.ndarray, edge_views: np.ndarray, batch: pg.EdgeBatch | pg.ObservedMatches,
                   free: np.ndarray, max_iterations: int, step_tolerance: float) -> tuple[np.ndarray, int]:
    """LM on Σ_e λ_min(Pˢ_e(R_j R_i^T)) (bearing-normalised θ): per-edge normal equations
    from kernels.epipolar_normal_equations chained to the cameras, JᵀJ = Cᵀ diag(JᵀJ_e) C."""
    n = R.shape[0]
    R_ij = R[edge_views[:, 1]] @ np.swapaxes(R[edge_views[:, 0]], 1, 2)
    ev = _epipolar_terms(R_ij, batch)
    cost = float(ev.cost.sum())
    mu = 1e-4
    it = 0
    for it in range(1, max_iterations + 1):
        C = chain_matrix(R, edge_views, n)
        JtJ = (C.T @ _block_diag(ev.JtJ) @ C).tocsc()[free][:, free]
        grad = (C.T @ ev.Jtr.ravel())[free]
        while True:
            delta_free = _solve_damped(JtJ, grad, mu)
            if delta_free is not None:
                delta = np.zeros(3 * n)
                delta[free] = delta_free
                R_cand = so3.exp(delta.reshape(n, 3)) @ R
                R_ij = R_cand[edge_views[:, 1]] @ np.swapaxes(R_cand[edge_views[:, 0]], 1, 2)
                ev_c = _epipolar_terms(R_ij, batch)
                if ev_c.cost.sum() <= cost:
                    break
            mu *= 10.0
            if mu > 1e10:
                return R, it
        step = float(np.max(np.linalg.norm(delta.reshape(n, 3), axis=1)))
        R, ev, cost, mu = R_cand, ev_c, float(ev_c.cost.sum()), max(mu / 10.0, 1e-15)
        log.debug("GRRM λ_min phase iteration %d: cost %.6e, max step %.2e rad", it, cost, step)
        if step < step_tolerance:
            break
    return R, it


def optimize_global_rotations(R_cam_from_world, edge_views, batch: pg.EdgeBatch | pg.ObservedMatches, obs_ids,
                              fixed_view: int = 0,
                              options: GRRMOptions = GRRMOptions(),
                              on_iteration: Callable[[dict], None] | None = None, peer_class=None) -> GRRMResult:
    """Alg. 4: minimise Σ_ik ρ(‖V_ik‖²) (eq:GRRMerror) over the rotations, one view fixed.
    ``batch``: the matches as an EdgeBatch, or as ObservedMatches (16 bytes per match; the
    same numbers);
    ``on_iteration``: called with each LM iteration's history entry (progress bars);
    ``peer_class``: a helper process for half the evaluation (GRRMSystem.parallel, e.g.
    runtime.parallel.ForkedPeer; the numbers do not depend on it), None: one process."""
    options.validate()
    R, edge_views, obs_ids = validate_inputs(R_cam_from_world, edge_views, batch, obs_ids)
    n = R.shape[0]
    if not 0 <= fixed_view < n:
        raise ValueError(f"fixed_view: must be in [0, {n})")
    problem = GRRMSystem(n, edge_views, batch, obs_ids, options.residual)
    with problem.parallel(peer_class):
        return _levenberg_marquardt(problem, R, edge_views, batch, fixed_view, options, on_iteration)


def _levenberg_marquardt(problem: GRRMSystem, R: np.ndarray, edge_views: np.ndarray, batch: pg.EdgeBatch,
                         fixed_view: int, options: GRRMOptions,
                         on_iteration: Callable[[dict], None] | None) -> GRRMResult:
    """The body of :func:`optimize_global_rotations` on its problem (validated inputs)."""
    n = R.shape[0]
    free = np.ones(3 * n, dtype=bool)
    free[3 * fixed_view:3 * fixed_view + 3] = False
    R_input = R
    # costs only (no Jacobian) until the loss scale is settled
    V, S, _ = problem.evaluate(R, with_jacobian=False)
    sq = np.einsum("gk,gk->g", V, V)
    scale = options.loss_scale
    if scale is None:
        active = S > 0
        med = np.median(np.sqrt(sq[active])) if np.any(active) else 0.0
        scale = max(options.loss_scale_factor * 1.4826 * med, 1e-12)
    cost = float(robust_rho(sq, options.loss, scale)[0].sum())  # without translation weights

    def linearize(R_at: np.ndarray, with_jacobian: bool, exact: bool = False):
        # (robust cost, JᵀWJ, JᵀWV, remainder) of all 3n parameters
        return problem.linearize(R_at, options.loss, scale, options.robust_hessian, with_jacobian, exact)

    def weighted_batch(R_at: np.ndarray) -> pg.EdgeBatch:
        # each edge's t from Σ w θθᵀ with Huber IRLS weights of its matches (weight 1 within
        # 3 robust sigmas, so clean data is untouched): wrong matches with large θ would
        # otherwise tilt t for the whole edge. Weighed at the chosen start, after the λ_min
        # phase (weights from a start far off would down-weight good matches).
        if not (options.robust_translation and batch.num_edges):
            return batch
        return batch.with_weights(problem.translation_weights(R_at, batch))

    def restrict(H):  # the free parameters' rows and columns
        if H is None:
            return None
        return H[np.ix_(free, free)] if isinstance(H, np.ndarray) else H[free][:, free]

    exact_failed = False  # the exact Hessian's model has raised the cost once in this problem

    def lm_iteration(R_at: np.ndarray, cost_now: float, JtJ, grad, remainder, mu: float):
        """Alg. 4's inner loop: solve, evaluate, raise the damping until the cost decreases.
        Returns (accepted, R, cost, JᵀWJ, JᵀWV, remainder, step, damping) of the candidate."""
        nonlocal exact_failed
        JtJ, remainder = restrict(JtJ), restrict(remainder)
        grad = grad[free]
        retry = False
        while True:
            delta_free = _solve_damped(JtJ, grad, mu, remainder)
            if delta_free is not None:
                delta = np.zeros(3 * n)
                delta[free] = delta_free
                R_cand = so3.exp(delta.reshape(n, 3)) @ R_at
                step = float(np.max(np.linalg.norm(delta.reshape(n, 3), axis=1)))
                # an iteration's first candidate comes with its normal equations (accepted
                # steps, the usual case, reuse them), except after a step below
                # step_tolerance, after which LM stops if it is accepted. A retry (without
                # the exact term, or at a higher damping) is costed alone first (a quarter of
                # a linearisation): near the optimum a rejected candidate would otherwise
                # cost a full Jacobian. So is an exact model's candidate once that model has
                # failed: where it fails it tends to fail again (the 200-view circle: in
                # iterations 2 and 3, each time a full Jacobian thrown away)
                with_jacobian = step >= options.step_tolerance
                exact = step < options.exact_curvature_below
                if retry or (exact_failed and remainder is not None):
                    cost_c, JtJ_c, grad_c, rem_c = linearize(R_cand, False)
                    if cost_c <= cost_now and with_jacobian:
                        cost_c, JtJ_c, grad_c, rem_c = linearize(R_cand, True, exact)
                else:
                    cost_c, JtJ_c, grad_c, rem_c = linearize(R_cand, with_jacobian, exact)
                if cost_c <= cost_now:
                    return True, R_cand, cost_c, JtJ_c, grad_c, rem_c, step, max(mu / 10.0, 1e-15)
            retry = True
            if remainder is not None:
                exact_failed = True
                # the exact Hessian's model failed: the clamped PSD model at the same
                # damping before any more damping (it is accepted where the exact model fails
                # up to far more damping)
                remainder = None
                continue
            mu *= 10.0
            if mu > options.max_damping:
                return False, R_at, cost_now, None, None, None, 0.0, mu

    def descend(R: np.ndarray, first, start) -> GRRMResult:
        """Alg. 4's LM iterations from ``R`` (``first``: its first iteration, ``start``: its
        linearisation, when computed already; None: made here with R's translation weights)."""
        if start is None:
            problem.batch = weighted_batch(R)
            start = linearize(R, True, options.exact_curvature_below > 0)
        cost, JtJ, grad, remainder = start
        # the initial cost of the problem that is optimised (same weights and scale as the end)
        initial_cost = cost if R is R_input else linearize(R_input, False)[0]
        history: list[dict] = []
        mu = options.initial_damping
        converged = False
        iteration = 0
        log.debug("GRRM start: %d views, %d edges, %d observations, cost %.6e, loss %s (scale %.3e)",
                 n, batch.num_edges, problem.num_groups, cost, options.loss, scale)
        for iteration in range(1, options.max_iterations + 1):
            t0 = time.perf_counter()
            if iteration == 1 and first is not None:
                accepted, R_cand, cost_c, JtJ_c, grad_c, rem_c, step, mu, seconds = first
                t0 -= seconds
            else:
                accepted, R_cand, cost_c, JtJ_c, grad_c, rem_c, step, mu = lm_iteration(R, cost, JtJ, grad, remainder,
                                                                                        mu)
            if not accepted:
                history.append({"iteration": iteration, "cost": cost, "step": 0.0, "damping": mu, "accepted": False,
                                "seconds": time.perf_counter() - t0})
                if on_iteration is not None:
                    on_iteration(history[-1])
                log.debug("GRRM iteration %d: no decrease possible (damping %.1e); stop", iteration, mu)
                converged = True
                break
            decrease = cost - cost_c
            R, cost, JtJ, grad, remainder = R_cand, cost_c, JtJ_c, grad_c, rem_c
            history.append({"iteration": iteration, "cost": cost, "step": step, "damping": mu, "accepted": True,
                            "seconds": time.perf_counter() - t0})
            if on_iteration is not None:
                on_iteration(history[-1])
            log.debug("GRRM iteration %d: cost %.6e (-%.2e), max step %.2e rad, %.2f s",
                     iteration, cost, decrease, step, time.perf_counter() - t0)
            if decrease <= options.function_tolerance * max(cost, 1e-300) or step < options.step_tolerance:
                converged = True
                break
        return GRRMResult(R_cam_from_world=R, initial_cost=initial_cost, cost=cost, iterations=iteration,
                          converged=converged, history=history, num_observations=problem.num_groups, loss_scale=scale,
                          processes=problem.processes)

    first = None  # GRRM's first iteration from the input start, when computed before the λ_min phase
    start = None  # (cost, JᵀWJ, JᵀWV, remainder) at the chosen start, with its translation weights
    if options.epipolar_max_iterations > 0 and batch.num_edges:
        if options.epipolar_trigger is not None and options.max_iterations > 0:
            # GRRM's own first step from the input start decides whether the λ_min phase is
            # needed: an accepted step (no extra damping) below epipolar_trigger means the
            # start is already in GRRM's basin, where the λ_min phase cannot help
            problem.batch = weighted_batch(R_input)
            start = linearize(R_input, True, options.exact_curvature_below > 0)
            t0 = time.perf_counter()
            first = lm_iteration(R_input, *start, options.initial_damping) + (time.perf_counter() - t0,)
            accepted, step, mu = first[0], first[6], first[7]
            in_basin = accepted and mu < options.initial_damping and step <= options.epipolar_trigger
            if in_basin:
                log.debug("GRRM λ_min phase: skipped (first GRRM step %.2e rad <= %.2e)", step,
                         options.epipolar_trigger)
        if first is None or not in_basin:
            # the λ_min phase only proposes a start: keep it if GRRM's own cost (without the
            # translation weights, which depend on the start) agrees it is better (on weak
            # geometry, e.g. far points, λ_min's optimum can be worse)
            weighted, problem.batch = problem.batch, batch
            R1, it1 = epipolar_phase(R, edge_views, batch, free, options.epipolar_max_iterations,
                                     options.epipolar_step_tolerance)
            cost1 = problem.linearize(R1, options.loss, scale, False, False)[0]
            if cost1 < cost:
                from_input = (weighted, first, start)  # for the descent from the input start below
                R, cost, first, start = R1, cost1, None, None
            else:
                problem.batch = weighted  # the start is kept: so are its weights and first iteration
            log.debug("GRRM λ_min phase: %d iterations, start %s", it1, "taken" if R is R1 else "kept")
    result = descend(R, first, start)
    if R is not R_input:
        # The λ_min phase's start has the lower cost, but the descent from it can end in a
        # worse minimum than the descent from the input start would have. Both descents; the lower final cost
        # (the same loss scale, without the start-dependent translation weights) is kept.
        problem.batch = from_input[0]
        other = descend(R_input, *from_input[1:])
        problem.batch = batch
        ends = [problem.linearize(r.R_cam_from_world, options.loss, scale, False, False)[0] for r in (result, other)]
        result = replace(result, start="lambda_min") if ends[0] <= ends[1] else other
        log.debug("GRRM: final cost from the λ_min phase's start %.6e, from the input start %.6e: the %s kept",
                  ends[0], ends[1], "first" if result.start == "lambda_min" else "second")
        result.descents = 2
    return result


def grrm_residuals(R_cam_from_world, edge_views, batch: pg.EdgeBatch, obs_ids, with_jacobian: bool = False,
                   residual: str = "bearing"):
    """V_ik (G, 3) of eq:GRRMRes2 for every observation (order: sorted unique ids; ``residual``
    as GRRMOptions.residual) and,
    optionally, the explicit sparse Jacobian J = J_e C (3G x 3n, left perturbations of the
    cameras) — for tests and small problems; the optimiser never forms it."""
    R, edge_views, obs_ids = validate_inputs(R_cam_from_world, edge_views, batch, obs_ids)
    problem = GRRMSystem(R.shape[0], edge_views, batch, obs_ids, residual)
    V, _, B = problem.evaluate(R, with_jacobian)
    if not with_jacobian:
        return V, None
    nc = B.shape[1]
    blocks = B.T.reshape(nc, 3, 3)
    rows = (3 * problem.contribution_groups())[:, None, None] + np.arange(3)[None, :, None]
    cols = (3 * problem.contribution_edges())[:, None, None] + np.arange(3)[None, None, :]
    J_e = sp.csr_matrix((blocks.ravel(), (np.broadcast_to(rows, (nc, 3, 3)).ravel(),
                                          np.broadcast_to(cols, (nc, 3, 3)).ravel())),
                        shape=(3 * problem.num_groups, 3 * problem.E))
    return V, (J_e @ problem.chain_matrix(R)).tocsr()
