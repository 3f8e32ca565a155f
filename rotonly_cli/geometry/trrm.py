"""TRRM two-view rotation optimisation (paper Alg. 1-2), batched in lock-step over edges.

Levenberg-Marquardt on the rotation manifold: R_ij <- exp([δ]x) R_ij, with the exact
Jacobian of :func:`rotonly_cli.geometry.twoview.trrm_residuals`. Every edge keeps its own
damping and its own convergence test; converged edges leave the batch, so the remaining
iterations only touch the matches of edges still moving.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import twoview as tv
from rotonly_cli.geometry.scene import (Identification, IdentificationOptions, SceneKind, classify,
                                        detection_values, kind_mask, pure_rotation_ratios)


@dataclass(frozen=True)
class TRRMOptions:
    max_iterations: int = 50  #: k_max of Alg. 2
    function_tolerance: float = 1e-12  #: stop when the relative cost decrease is below this (ε of Alg. 2)
    #: stop after an accepted step shorter than this (rad). With noise LM converges linearly
    #: (measured ~8x per iteration at 1 px), so the remaining error is ~tol/8 = 1e-8 rad,
    #: four orders below the noise-level error; noise-free it converges quadratically.
    step_tolerance: float = 1e-7
    gradient_tolerance: float = 1e-14  #: stop when ‖J^T r‖ / (cost + tiny) is below this
    initial_damping: float = 1e-4  #: μ relative to the diagonal of J^T J (Marquardt scaling)
    min_damping: float = 1e-12
    max_damping: float = 1e8
    #: first phase on the smooth λ_min(Pˢ) cost (twoview.epipolar_residuals) before TRRM, so
    #: that starts several degrees off still reach TRRM's basin; 0 disables it.
    epipolar_max_iterations: int = 30
    #: the first phase only has to reach TRRM's basin: it stops at steps below this (rad)
    #: or at a relative decrease below ``epipolar_function_tolerance``.
    epipolar_step_tolerance: float = 1e-4
    epipolar_function_tolerance: float = 1e-4
    #: robust TRRM: "cauchy" (IRLS) or "none" (the paper's plain least squares). Real matches
    #: contain wrong correspondences and points near the epipole whose analytic depth
    #: (eq:analyticalDepth) is noise-dominated: their bearing residuals reach O(1) and, squared,
    #: outweigh hundreds of good matches — both in the cost and in Pˢ, which then gives a
    #: wrong t for everyone. IRLS weights w = 1/(1 + s/c²) enter Pˢ (Σ w θθᵀ: the noise-free
    #: null vector is unchanged by any positive weights) and the residual rows.
    loss: str = "cauchy"
    #: Cauchy scale c = loss_scale_factor x 1.4826 x the edge's median per-match residual norm
    loss_scale_factor: float = 3.0
    #: floor of c (bearing units); noise-free data would otherwise get c = 0
    min_loss_scale: float = 1e-9
    #: IRLS rounds: weights are re-estimated and LM re-run this many times
    irls_rounds: int = 2

    def validate(self) -> "TRRMOptions":
        if self.loss not in ("cauchy", "none"):
            raise ValueError(f"loss: must be 'cauchy' or 'none', got {self.loss!r}")
        if self.max_iterations < 0:
            raise ValueError("max_iterations: must be >= 0")
        for name in ("function_tolerance", "step_tolerance", "gradient_tolerance", "initial_damping"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}: must be >= 0")
        return self


@dataclass
class TRRMResult:
    rotations: np.ndarray  # (E, 3, 3) refined R_j_from_i
    translation_directions: np.ndarray  # (E, 3) unit t_ij (zeros for PURE_ROTATION)
    initial_cost: np.ndarray  # (E,)
    cost: np.ndarray  # (E,) final eq:ROMerr (pure-rotation cost for PURE_ROTATION edges)
    iterations: np.ndarray  # (E,) LM iterations used
    converged: np.ndarray  # (E,) bool
    kinds: np.ndarray  # (E,) SceneKind
    identification: Identification


def optimize_rotations(R_init: np.ndarray, batch: tv.EdgeBatch, options: TRRMOptions = TRRMOptions(),
                       edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Alg. 2's LM on eq:ROMerr for the selected ``edges`` (default all), in lock-step, after
    an optional first phase on λ_min(Pˢ) (``options.epipolar_max_iterations``).

    Returns (R (E,3,3), initial_cost (E,), cost (E,), iterations (E,), converged (E,)) where
    the costs are TRRM costs and iterations count both phases.
    """
    E = batch.num_edges
    R = np.array(R_init, dtype=float, copy=True).reshape(E, 3, 3)
    sel = np.arange(E) if edges is None else np.asarray(edges, dtype=np.int64)
    initial_cost = np.zeros(E)
    if sel.size:
        sub = batch.subset(sel) if sel.size != E else batch
        initial_cost[sel] = kernels.trrm_normal_equations(R[sel], sub, with_jacobian=False).cost
    phase1 = TRRMOptions(**{**options.__dict__, "max_iterations": options.epipolar_max_iterations,
                             "step_tolerance": options.epipolar_step_tolerance,
                             "function_tolerance": options.epipolar_function_tolerance})
    if options.loss == "none" or sel.size == 0:
        iters0 = np.zeros(E, dtype=np.int64)
        if options.epipolar_max_iterations > 0:
            R, _, _, iters0, _ = lm_on_rotations(R, batch, kernels.epipolar_normal_equations, phase1, edges)
        R, _, cost, iters, conv = lm_on_rotations(R, batch, kernels.trrm_normal_equations, options, edges)
        return R, initial_cost, cost, iters + iters0, conv
    R0 = np.array(R_init, dtype=float).reshape(E, 3, 3)
    sub = batch.subset(sel) if sel.size != E else batch
    # weights at the start: t from unit-length θ first (each match one vote, so a few wrong
    # matches with large θ cannot dictate t), then one refinement with Cauchy weights
    w = robust_match_weights(R0[sel], sub, None, options)
    w = robust_match_weights(R0[sel], sub, w, options)
    weights = np.ones(batch.x_i.shape[0])
    weights[_match_index(batch, sel)] = w
    weighted = batch.with_weights(weights)
    R = R0.copy()
    iters0 = np.zeros(E, dtype=np.int64)
    if options.epipolar_max_iterations > 0:
        R, _, _, iters0, _ = lm_on_rotations(R, weighted, kernels.epipolar_normal_equations, phase1, edges)
    iters = np.zeros(E, dtype=np.int64)
    conv = np.zeros(E, dtype=bool)
    for round_ in range(max(1, options.irls_rounds)):
        R, _, _, it, conv = lm_on_rotations(R, weighted, kernels.trrm_normal_equations, options, edges)
        iters += it
        if round_ + 1 < options.irls_rounds:
            w = robust_match_weights(R[sel], sub, weights[_match_index(batch, sel)], options)
            weights[_match_index(batch, sel)] = w
            weighted = batch.with_weights(weights)
    # both costs with the final weights, so that they compare
    sub_w = weighted.subset(sel) if sel.size != E else weighted
    cost = np.zeros(E)
    cost[sel] = kernels.trrm_normal_equations(R[sel], sub_w, with_jacobian=False).cost
    initial_cost[sel] = kernels.trrm_normal_equations(R0[sel], sub_w, with_jacobian=False).cost
    return R, initial_cost, cost, iters + iters0, conv


def _match_index(batch: tv.EdgeBatch, edges: np.ndarray) -> np.ndarray:
    counts = batch.counts[edges]
    starts = batch.offsets[:-1][edges]
    within = np.arange(counts.sum()) - np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return np.repeat(starts, counts) + within


def robust_match_weights(R: np.ndarray, batch: tv.EdgeBatch, ps_weights: np.ndarray | None,
                         options: TRRMOptions, kind: str = "cauchy") -> np.ndarray:
    """Cauchy IRLS weights 1/(1 + s/c²) of every match from its TRRM residual s = ‖r‖²,
    with t the null vector of Σ w θθᵀ (``ps_weights`` w; None: w = 1/‖θ‖², unit θ) and c
    from the edge's median residual (options.loss_scale_factor)."""
    if ps_weights is None:
        theta = tv.theta_vectors(R, batch)
        n2 = np.einsum("ma,ma->m", theta, theta)
        ps_weights = 1.0 / np.maximum(n2, 1e-300)
    terms = kernels.trrm_match_terms(R, batch.with_weights(ps_weights), with_jacobian=False)
    sq = np.einsum("mk,mk->m", terms["r"], terms["r"])
    c = np.maximum(options.loss_scale_factor * 1.4826 * np.sqrt(tv.segment_median(sq, batch)), options.min_loss_scale)
    c2 = np.repeat(c * c, batch.counts)
    if kind == "huber":  # weight 1 inside c: clean data keeps its plain least-squares Pˢ
        return np.minimum(1.0, np.sqrt(c2 / np.maximum(sq, 1e-300)))
    return 1.0 / (1.0 + sq / c2)


def lm_on_rotations(R_init: np.ndarray, batch: tv.EdgeBatch, residual_fn, options: TRRMOptions = TRRMOptions(),
                    edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lock-step LM on the rotation manifold for any per-edge least-squares ``residual_fn``
    (returning a ResidualEvaluation with cost, JtJ, Jtr) on the selected ``edges``.
    Per-match weights travel with ``batch.weights`` (kept through the subsets).

    Per-edge damping and convergence; converged edges leave the batch. Returns
    (R, initial_cost, cost, iterations, converged); unselected edges are untouched.
    """
    options.validate()
    E = batch.num_edges
    R = np.array(R_init, dtype=float, copy=True).reshape(E, 3, 3)
    iterations = np.zeros(E, dtype=np.int64)
    converged = np.zeros(E, dtype=bool)
    initial_cost = np.zeros(E)
    final_cost = np.zeros(E)
    active = np.arange(E) if edges is None else np.asarray(edges, dtype=np.int64)
    if active.size == 0:
        return R, initial_cost, final_cost, iterations, converged
    sub = batch.subset(active) if active.size != E else batch
    ev = residual_fn(R[active], sub, with_jacobian=True)
    cost, JtJ, Jtr = ev.cost, ev.JtJ, ev.Jtr
    initial_cost[active] = cost
    final_cost[active] = cost
    mu = np.full(active.size, options.initial_damping)
    for _ in range(options.max_iterations):
        if active.size == 0:
            break
        diag = np.einsum("eii->ei", JtJ)
        damp = mu[:, None] * np.maximum(diag, 1e-12 * (diag.max(axis=1, keepdims=True) + 1e-300))
        A = JtJ + damp[:, :, None] * np.eye(3)
        delta = -np.linalg.solve(A, Jtr[:, :, None])[:, :, 0]
        R_cand = so3.exp(delta) @ R[active]
        ev_c = residual_fn(R_cand, sub, with_jacobian=True)
        iterations[active] += 1
        accept = ev_c.cost <= cost
        step = np.linalg.norm(delta, axis=1)
        decrease = cost - ev_c.cost
        # convergence: small relative decrease on an accepted step, tiny step, or tiny gradient
        done = (accept & (decrease <= options.function_tolerance * np.maximum(cost, 1e-300))) \
            | (step < options.step_tolerance) \
            | (np.linalg.norm(Jtr, axis=1) <= options.gradient_tolerance * (cost + 1e-300)) \
            | (mu >= options.max_damping)
        # accept the candidate where it is no worse
        R[active[accept]] = R_cand[accept]
        cost = np.where(accept, ev_c.cost, cost)
        JtJ = np.where(accept[:, None, None], ev_c.JtJ, JtJ)
        Jtr = np.where(accept[:, None], ev_c.Jtr, Jtr)
        mu = np.where(accept, np.maximum(mu / 10.0, options.min_damping), mu * 10.0)
        final_cost[active] = cost
        converged[active[done]] = True
        keep = ~done
        if not np.all(keep):
            keep_idx = np.flatnonzero(keep)
            active = active[keep_idx]
            sub = sub.subset(keep_idx)
            cost, JtJ, Jtr, mu = cost[keep_idx], JtJ[keep_idx], Jtr[keep_idx], mu[keep_idx]
    return R, initial_cost, final_cost, iterations, converged


def refine(R_init: np.ndarray, batch: tv.EdgeBatch, options: TRRMOptions = TRRMOptions(),
           identification_options: IdentificationOptions = IdentificationOptions()) -> TRRMResult:
    """Alg. 2 for every edge:

    1. RotationSingular (v_rs, independent of the rotation): returned unchanged (Alg. 2:
       "if Holoplane, return"; RankRegular-line likewise, paper §"Scene Identification").
    2. Every other edge: LM on eq:ROMerr.
    3. PR/B/I is decided at the *refined* rotation (the ratio ρ compares the two models at
       their optima; a poor start would otherwise read as "TRRM explains nothing better"),
       and for those edges the pure-rotation bearing cost (eq:PureRotationReprojBearingError)
       is minimised in closed form (orthogonal Procrustes) instead; t = 0.
    """
    identification_options.validate()
    E = batch.num_edges
    R_init = np.asarray(R_init, dtype=float).reshape(E, 3, 3)
    v_rs = detection_values(batch)
    singular = v_rs < identification_options.rotation_singular_threshold
    candidates = np.flatnonzero(~singular)
    R, c0, c1, iters, conv = optimize_rotations(R_init, batch, options, edges=candidates)
    rho = np.full(E, np.inf)
    rho[singular] = pure_rotation_ratios(R_init[singular], batch.subset(np.flatnonzero(singular))) \
        if singular.any() else rho[singular]
    if candidates.size:
        sub = batch.subset(candidates) if candidates.size != E else batch
        rho[candidates] = pure_rotation_ratios(R[candidates], sub)
    kinds = classify(v_rs, rho, identification_options)
    regular = np.flatnonzero(kind_mask(kinds, SceneKind.REGULAR))
    pure = np.flatnonzero(kind_mask(kinds, SceneKind.PURE_ROTATION))
    t = np.zeros((E, 3))
    if regular.size:
        sub = batch.subset(regular) if regular.size != E else batch
        t_reg, _, _ = tv.translation_directions(R[regular], sub)
        t[regular] = t_reg
    if pure.size:
        sub = batch.subset(pure)
        R_pure = tv.best_pure_rotation(sub)
        c0[pure] = tv.pure_rotation_residuals(R_init[pure], sub)
        c1[pure] = tv.pure_rotation_residuals(R_pure, sub)
        R[pure] = R_pure
        conv[pure] = True
    if singular.any():
        idx = np.flatnonzero(singular)
        c0[idx] = c1[idx] = kernels.trrm_normal_equations(R_init[idx], batch.subset(idx), with_jacobian=False).cost
        conv[idx] = True
    eig = tv.symmetric_eigenvalues3(tv.ps_matrices(R, batch))
    ident = Identification(kinds=kinds, detection_value=v_rs, pure_rotation_ratio=rho, ps_eigenvalues=eig)
    return TRRMResult(rotations=R, translation_directions=t, initial_cost=c0, cost=c1, iterations=iters,
                      converged=conv, kinds=kinds, identification=ident)
