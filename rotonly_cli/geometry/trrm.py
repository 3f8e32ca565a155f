"""TRRM two-view rotation optimisation (paper Alg. 1-2), batched in lock-step over edges.

Levenberg-Marquardt on the rotation manifold: R_ij <- exp([δ]x) R_ij, with the exact
Jacobian of :func:`rotonly_cli.geometry.pairwise.trrm_residuals` (computed by the lean
evaluator kernels.trrm_evaluate). Every edge keeps its own damping and its own convergence
test; converged edges leave the batch, so the remaining iterations only touch the matches
of edges still moving. The λ_min(Pˢ) first phase runs on per-edge moments (O(1) per edge
and iteration); the robust loss re-runs LM with IRLS weights from the residuals of the
previous round's last accepted evaluation, then (``final_inlier_pass``) once more on plain
least squares over the matches within k σ of the IRLS result.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.identification import (
    Identification,
    IdentificationOptions,
    SceneKind,
    classify,
    detection_values,
    kind_mask,
    ratios_and_ps,
)
from rotonly_cli.options import TRRMOptions


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


class _TRRMProblem:
    """eq:ROMerr of some edges, for :func:`_lock_step_lm`: evaluates on a compacted copy of
    the match table (recut when fewer than half of its edges are still moving) and keeps
    every match's ‖r‖² at the accepted rotation (``sq``: the input of the next IRLS round)."""

    def __init__(self, table: kernels.MatchTable):
        # positions of the per-match ‖r‖² are this table's own (match_pos renumbered)
        table = kernels.MatchTable(table.data, table.offsets, table.weights, None, table.chunk)
        self.full = table
        self.cur = table
        self.pos = np.arange(table.num_edges)  # edge of the problem -> edge of self.cur
        self.sq = np.zeros(table.data.shape[1])
        self._sq_candidate = np.zeros(table.data.shape[1])

    def evaluate(self, R: np.ndarray, rows: np.ndarray, mode: np.ndarray):
        """Cost, JᵀJ and Jᵀr of ``rows`` at R; ``mode`` per edge: kernels.COST, GRADIENT (JᵀJ
        returned as zeros) or NORMAL."""
        if rows.size * 2 <= self.cur.num_edges:
            self.cur = self.full.subset(rows)
            self.pos = np.full(self.full.num_edges, -1)
            self.pos[rows] = np.arange(rows.size)
            self._sq_candidate = np.zeros(self.cur.data.shape[1])
        n = self.cur.num_edges
        at = self.pos[rows]
        R_cur = np.zeros((n, 3, 3))
        R_cur[at] = R
        jac = np.zeros(n, dtype=bool)
        jac[at] = mode == kernels.NORMAL
        grad = np.zeros(n, dtype=bool)
        grad[at] = mode == kernels.GRADIENT
        ev = np.zeros(n, dtype=bool)
        ev[at] = True
        out = kernels.trrm_evaluate(R_cur, self.cur, jacobian=jac, gradient=grad, evaluate=ev,
                                    sq_out=self._sq_candidate)
        JtJ = out["JtJ"][at] if "JtJ" in out else np.zeros((rows.size, 3, 3))
        Jtr = out["Jtr"][at] if "Jtr" in out else np.zeros((rows.size, 3))
        return out["cost"][at], JtJ, Jtr

    def commit(self, rows: np.ndarray) -> None:
        """The candidates of ``rows`` were accepted: keep their per-match ‖r‖²."""
        if rows.size == 0:
            return
        if rows.size == self.cur.num_edges:  # every edge of the current table: no per-match mask
            if self.cur is self.full:
                np.copyto(self.sq, self._sq_candidate)
            else:
                self.sq[self.cur.match_pos] = self._sq_candidate
            return
        mask = np.zeros(self.cur.num_edges, dtype=bool)
        mask[self.pos[rows]] = True
        matches = np.repeat(mask, self.cur.counts)
        self.sq[self.cur.match_pos[matches]] = self._sq_candidate[matches]


class _MomentProblem:
    """λ_min(Pˢ) of bearing-normalised θ from per-edge moments (kernels.epipolar_from_moments):
    O(1) work per edge and iteration."""

    def __init__(self, moments: np.ndarray):
        self.moments = moments

    def evaluate(self, R: np.ndarray, rows: np.ndarray, mode: np.ndarray):
        out = kernels.epipolar_from_moments(R, self.moments[rows])  # always NORMAL: O(1) per edge
        return out["cost"], out["JtJ"], out["Jtr"]

    def commit(self, rows: np.ndarray) -> None:
        pass


def _lock_step_lm(problem, R_init: np.ndarray, options: TRRMOptions):
    """Levenberg-Marquardt on R <- exp([δ]x) R for every edge of ``problem`` in lock-step:
    per-edge damping and stopping rules, finished edges leave the batch. A candidate after a
    step below ``options.frozen_hessian_below`` from a fresh JᵀJ computes only the exact
    gradient Jᵀr and keeps that JᵀJ for one iteration.

    A candidate whose acceptance would end its edge (its step, or the step the observed
    contraction predicts after it, is below ``step_tolerance``) is evaluated without the
    Jacobian: only its cost decides. Returns (R, initial_cost, cost, iterations, converged)."""
    n = R_init.shape[0]
    R = np.array(R_init, dtype=float, copy=True)
    iterations = np.zeros(n, dtype=np.int64)
    converged = np.zeros(n, dtype=bool)
    active = np.arange(n)
    if n == 0:
        return R, np.zeros(0), np.zeros(0), iterations, converged
    cost, JtJ, Jtr = problem.evaluate(R, active, np.full(n, kernels.NORMAL))
    problem.commit(active)
    initial_cost = cost.copy()
    final_cost = cost.copy()
    mu = np.full(n, options.initial_damping)
    last_step = np.full(n, np.inf)  # previous step when it was accepted, else inf
    fresh = np.ones(n, dtype=bool)  # JᵀJ was computed at the current rotation
    model_ok = np.zeros(n, dtype=bool)  # the last accepted step decreased the cost as modelled
    eye = np.eye(3)
    for _ in range(options.max_iterations):
        if active.size == 0:
            break
        diag = np.einsum("eii->ei", JtJ)
        damp = mu[:, None] * np.maximum(diag, 1e-12 * (diag.max(axis=1, keepdims=True) + 1e-300))
        delta = -np.linalg.solve(JtJ + damp[:, :, None] * eye, Jtr[:, :, None])[:, :, 0]
        step = np.linalg.norm(delta, axis=1)
        # linear convergence at rate κ = step / last_step leaves about step κ / (1 - κ) to go
        kappa = step / last_step
        # trusted only in the Gauss-Newton regime: damping not above its start, fast
        # contraction (κ < 0.1) and a previous step whose cost decrease matched the
        # quadratic model (gain ratio in [0.5, 1.5]). Heavily damped or irregular progress in
        # a rugged valley says little about the distance left (Standard 5 px trials of
        # rotonly bench twoview stopped 1e-4 rad short without these conditions).
        trusted = (kappa < 0.1) & np.isfinite(last_step) & (mu <= options.initial_damping) & model_ok
        predicted = np.where(trusted, step * kappa / (1.0 - kappa), np.inf)
        small = step < options.step_tolerance
        ends_if_accepted = small | ((step < options.contraction_stop_below) & (predicted < options.step_tolerance))
        R_cand = so3.exp(delta) @ R[active]
        reuse = (step < options.frozen_hessian_below) & fresh
        mode = np.where(ends_if_accepted, kernels.COST, np.where(reuse, kernels.GRADIENT, kernels.NORMAL))
        cost_c, JtJ_c, Jtr_c = problem.evaluate(R_cand, active, mode)
        iterations[active] += 1
        accept = cost_c <= cost
        decrease = cost - cost_c
        # decrease predicted by the Gauss-Newton model of Σ r²: -2 δᵀJᵀr - δᵀJᵀJδ
        model = -2.0 * np.einsum("ei,ei->e", delta, Jtr) - np.einsum("ei,eij,ej->e", delta, JtJ, delta)
        gain = decrease / np.where(model > 0, model, np.inf)
        done = small | (accept & ends_if_accepted) \
            | (accept & (decrease <= options.function_tolerance * np.maximum(cost, 1e-300))) \
            | (np.linalg.norm(Jtr, axis=1) <= options.gradient_tolerance * (cost + 1e-300)) \
            | (mu >= options.max_damping)
        R[active[accept]] = R_cand[accept]
        problem.commit(active[accept])
        cost = np.where(accept, cost_c, cost)
        JtJ = np.where((accept & (mode == kernels.NORMAL))[:, None, None], JtJ_c, JtJ)
        Jtr = np.where(accept[:, None], Jtr_c, Jtr)
        mu = np.where(accept, np.maximum(mu / 10.0, options.min_damping), mu * 10.0)
        last_step = np.where(accept, step, np.inf)
        model_ok = accept & (gain >= 0.5) & (gain <= 1.5)
        fresh = np.where(accept, mode == kernels.NORMAL, fresh)
        final_cost[active] = cost
        converged[active[done]] = True
        keep = np.flatnonzero(~done)
        if keep.size < active.size:
            active = active[keep]
            cost, JtJ, Jtr, mu, last_step, fresh, model_ok = cost[keep], JtJ[keep], Jtr[keep], mu[keep], \
                last_step[keep], fresh[keep], model_ok[keep]
    return R, initial_cost, final_cost, iterations, converged


def _phase1_options(options: TRRMOptions) -> TRRMOptions:
    return TRRMOptions(**{**options.__dict__, "max_iterations": options.epipolar_max_iterations,
                          "step_tolerance": options.epipolar_step_tolerance,
                          "function_tolerance": options.epipolar_function_tolerance,
                          "contraction_stop_below": 0.0, "frozen_hessian_below": 0.0})  # O(1) per edge anyway


def optimize_rotations(R_init: np.ndarray, batch: pg.EdgeBatch, options: TRRMOptions = TRRMOptions(),
                       edges: np.ndarray | None = None, table: kernels.MatchTable | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Alg. 2's LM on eq:ROMerr for the selected ``edges`` (default all), in lock-step, after
    an optional first phase on λ_min(Pˢ) (``options.epipolar_max_iterations``).

    Returns (R (E,3,3), initial_cost (E,), cost (E,), iterations (E,), converged (E,)) where
    the costs are TRRM costs (robust loss: with the final weights, the 0/1 inlier weights
    of ``options.final_inlier_pass`` when it is on) and
    iterations count both phases. ``table``: kernels.MatchTable of the whole batch without
    weights, when the caller has one already.
    """
    options.validate()
    E = batch.num_edges
    R = np.array(R_init, dtype=float, copy=True).reshape(E, 3, 3)
    sel = np.arange(E) if edges is None else np.asarray(edges, dtype=np.int64)
    initial_cost = np.zeros(E)
    cost = np.zeros(E)
    iterations = np.zeros(E, dtype=np.int64)
    converged = np.zeros(E, dtype=bool)
    if sel.size == 0:
        return R, initial_cost, cost, iterations, converged
    sub = batch.subset(sel) if sel.size != E else batch
    if table is not None and sel.size != E:
        table = table.subset(sel)
    R0 = R[sel]
    if options.loss == "none":
        table = kernels.MatchTable.from_batch(sub)  # the batch's own weights, if any
    else:
        # weights at the start: t from unit-length θ first (each match one vote, so a few
        # wrong matches with large θ cannot dictate t), then one refinement with Cauchy weights
        table = kernels.MatchTable.from_batch(sub.with_weights(None)) if table is None else table.with_weights(None)
        sq = np.empty(sub.x_i.shape[0])
        kernels.trrm_evaluate(R0, table, unit_theta=True, sq_out=sq)
        table = table.with_weights(_cauchy_weights(sq, table, options))
        kernels.trrm_evaluate(R0, table, sq_out=sq)
        table = table.with_weights(_cauchy_weights(sq, table, options))
    if options.loss == "none":
        initial_cost[sel] = kernels.trrm_evaluate(R0, table)["cost"]
    R_sel = R0
    if options.epipolar_max_iterations > 0:
        R_sel, _, _, it, _ = _lock_step_lm(_MomentProblem(kernels.epipolar_moments(table)), R_sel,
                                           _phase1_options(options))
        iterations[sel] += it
    rounds = 1 if options.loss == "none" else max(1, options.irls_rounds)
    intermediate = options if options.irls_step_tolerance is None else \
        TRRMOptions(**{**options.__dict__, "step_tolerance": max(options.irls_step_tolerance, options.step_tolerance)})
    for round_ in range(rounds):
        problem = _TRRMProblem(table)
        R_sel, _, c1, it, conv = _lock_step_lm(problem, R_sel, options if round_ + 1 == rounds else intermediate)
        iterations[sel] += it
        if round_ + 1 < rounds:
            table = table.with_weights(_cauchy_weights(problem.sq, table, options))
    if options.loss != "none" and options.final_inlier_pass:
        # plain least squares on the inliers of the IRLS result (options.final_inlier_pass)
        table = table.with_weights(_inlier_weights(problem.sq, table, options))
        problem = _TRRMProblem(table)
        R_sel, _, c1, it, conv = _lock_step_lm(problem, R_sel, options)
        iterations[sel] += it
    R[sel] = R_sel
    cost[sel] = c1  # the last round's cost: the final rotations with the final weights
    converged[sel] = conv
    if options.loss != "none":  # both costs with the final weights, so that they compare
        initial_cost[sel] = kernels.trrm_evaluate(R0, table)["cost"]
    return R, initial_cost, cost, iterations, converged


def _cauchy_weights(sq: np.ndarray, table: kernels.MatchTable, options: TRRMOptions,
                    kind: str = "cauchy") -> np.ndarray:
    """IRLS weights from per-match squared residuals s: Cauchy 1/(1 + s/c²) (or Huber) with
    c = loss_scale_factor x 1.4826 x the edge's median residual norm (robust_match_weights)."""
    c = np.maximum(options.loss_scale_factor * 1.4826 * np.sqrt(kernels.segment_median(sq, table.offsets)),
                   options.min_loss_scale)
    c2 = np.repeat(c * c, table.counts)
    if kind == "huber":  # weight 1 inside c: clean data keeps its plain least-squares Pˢ
        return np.minimum(1.0, np.sqrt(c2 / np.maximum(sq, 1e-300)))
    return 1.0 / (1.0 + sq / c2)


def _inlier_weights(sq: np.ndarray, table: kernels.MatchTable, options: TRRMOptions) -> np.ndarray:
    """0/1 weights: 1 where ‖r‖ <= k σ, σ = 1.4826 x the edge's median residual norm (the
    robust scale of _cauchy_weights), k = options.inlier_threshold_sigmas; the threshold is
    floored at options.min_loss_scale so that noise-free edges keep every match."""
    sigma = 1.4826 * np.sqrt(kernels.segment_median(sq, table.offsets))
    threshold = np.maximum(options.inlier_threshold_sigmas * sigma, options.min_loss_scale)
    return (sq <= np.repeat(threshold * threshold, table.counts)).astype(float)


def robust_match_weights(R: np.ndarray, batch: pg.EdgeBatch, ps_weights: np.ndarray | None,
                         options: TRRMOptions, kind: str = "cauchy") -> np.ndarray:
    """Cauchy IRLS weights 1/(1 + s/c²) of every match from its TRRM residual s = ‖r‖²,
    with t the null vector of Σ w θθᵀ (``ps_weights`` w; None: w = 1/‖θ‖², unit θ) and c
    from the edge's median residual (options.loss_scale_factor)."""
    table = kernels.MatchTable.from_batch(batch.with_weights(ps_weights))
    sq = np.empty(batch.x_i.shape[0])
    kernels.trrm_evaluate(np.asarray(R, dtype=float).reshape(-1, 3, 3), table, unit_theta=ps_weights is None,
                          sq_out=sq)
    return _cauchy_weights(sq, table, options, kind)


def irls_match_weights(R: np.ndarray, batch: pg.EdgeBatch, kind: str = "cauchy") -> np.ndarray:
    """Two IRLS rounds of :func:`robust_match_weights` (the first with unit θ, the second with
    the first's weights in Pˢ): each match's robust weight in its edge's t (an edge's depend on
    its own matches only)."""
    first = robust_match_weights(R, batch, None, TRRMOptions(), kind=kind)
    return robust_match_weights(R, batch, first, TRRMOptions(), kind=kind)


def eight_point_rotations(batch: pg.EdgeBatch) -> np.ndarray:
    """(E, 2, 3, 3): per edge the two rotations of the linear 8-point essential matrix of all
    its matches (E = U diag(1, 1, 0) Vᵀ -> U W Vᵀ and U Wᵀ Vᵀ, signs fixed to det +1).
    Exact on noise-free data; a restart candidate for :func:`refine`."""
    a = (batch.x_j[:, :, None] * batch.x_i[:, None, :]).reshape(-1, 9)  # x_jᵀ E x_i = a · vec(E)
    starts = batch.offsets[:-1]
    AtA = np.stack([np.add.reduceat(a[:, r] * a[:, c], starts) for r in range(9) for c in range(9)],
                   axis=1).reshape(-1, 9, 9)
    E = np.linalg.eigh(AtA)[1][:, :, 0].reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(E)
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = np.stack([U @ W @ Vt, U @ W.T @ Vt], axis=1)
    return out * np.sign(np.linalg.det(out))[:, :, None, None]


def _median_sq_residual(R: np.ndarray, batch: pg.EdgeBatch) -> np.ndarray:
    r = pg.trrm_residuals(R, batch).residuals
    return pg.segment_median(np.einsum("mk,mk->m", r, r), batch)


def _take(result: TRRMResult, rows: np.ndarray, source: TRRMResult, source_rows: np.ndarray) -> None:
    """result[rows] = source[source_rows] for every per-edge array."""
    for name in ("rotations", "translation_directions", "initial_cost", "cost", "iterations", "converged", "kinds"):
        getattr(result, name)[rows] = getattr(source, name)[source_rows]
    for name in ("kinds", "detection_value", "pure_rotation_ratio", "ps_eigenvalues"):
        getattr(result.identification, name)[rows] = getattr(source.identification, name)[source_rows]


def _restart_suspicious(R_init: np.ndarray, batch: pg.EdgeBatch, result: TRRMResult, options: TRRMOptions,
                        identification_options: IdentificationOptions) -> TRRMResult:
    """TRRMOptions.restart_change_deg: edges that ended PURE_ROTATION or far from their start
    are refined again from the 8-point rotations; the lowest median squared residual wins if
    it is below half of the first result's. A start whose median squared residual is already
    above the first result's is not refined: LM from a worse start reaches a better minimum
    only by leaving its basin. On noisy edges started 1° off, half of which moved by more than
    1°, the linear 8-point rotations are all worse than TRRM's own optimum and the restarts
    made refine_rotations 5x slower for the same rotations (docs/tuning.md)."""
    change = np.degrees(so3.geodesic_angle(result.rotations, R_init))
    suspicious = ~kind_mask(result.kinds, SceneKind.ROTATION_SINGULAR) & (
        kind_mask(result.kinds, SceneKind.PURE_ROTATION) | (change > options.restart_change_deg))
    rows = np.flatnonzero(suspicious)
    if rows.size == 0:
        return result
    sub = batch.subset(rows)
    best = _median_sq_residual(result.rotations[rows], sub)
    # both 8-point starts of every suspicious edge in one batch (the edge twice): the edges
    # of a batch are refined independently, and a restart from a far start runs ~100 LM
    # iterations, whose cost is per-iteration overhead for a handful of edges
    starts = eight_point_rotations(sub)
    # (start, edge) pairs worth a refinement: the start is already below the first result
    tried = [(k, e) for k in (0, 1) for e in np.flatnonzero(_median_sq_residual(starts[:, k], sub) < best)]
    if not tried:
        return result
    which, edges = np.array([k for k, _ in tried]), np.array([e for _, e in tried])
    candidate = refine(starts[edges, which], batch.subset(rows[edges]), replace(options, restart_change_deg=None),
                       identification_options)
    median = _median_sq_residual(candidate.rotations, batch.subset(rows[edges]))
    for k in (0, 1):  # the starts in order, as before: the lower median wins
        own = np.flatnonzero(which == k)  # one row per edge within a start
        better = own[median[own] < 0.5 * best[edges[own]]]
        _take(result, rows[edges[better]], candidate, better)
        best[edges[better]] = median[better]
    return result


def refine(R_init: np.ndarray, batch: pg.EdgeBatch, options: TRRMOptions = TRRMOptions(),
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
    table = kernels.MatchTable.from_batch(batch.with_weights(None))
    R, c0, c1, iters, conv = optimize_rotations(R_init, batch, options, edges=candidates, table=table)
    # ρ of every edge at its rotation (singular edges keep R_init) and, from the same pass,
    # the plain Pˢ at the returned rotations for the identification eigenvalues
    rho, P_plain, t_plain = ratios_and_ps(R, batch, table)
    kinds = classify(v_rs, rho, batch.counts, identification_options)
    regular = np.flatnonzero(kind_mask(kinds, SceneKind.REGULAR))
    pure = np.flatnonzero(kind_mask(kinds, SceneKind.PURE_ROTATION))
    t = np.zeros((E, 3))
    t[regular] = t_plain[regular]  # closed-form t: plain Pˢ null vector, chirality sign
    if pure.size:
        sub = batch.subset(pure)
        R_pure = pg.best_pure_rotation(sub)
        c0[pure] = pg.pure_rotation_residuals(R_init[pure], sub)
        c1[pure] = pg.pure_rotation_residuals(R_pure, sub)
        R[pure] = R_pure
        conv[pure] = True
        P_plain[pure] = pg.ps_matrices(R_pure, sub)
    if singular.any():
        idx = np.flatnonzero(singular)
        c0[idx] = c1[idx] = kernels.trrm_normal_equations(R_init[idx], batch.subset(idx), with_jacobian=False).cost
        conv[idx] = True
    eig = pg.symmetric_eigenvalues3(P_plain)
    ident = Identification(kinds=kinds, detection_value=v_rs, pure_rotation_ratio=rho, ps_eigenvalues=eig)
    result = TRRMResult(rotations=R, translation_directions=t, initial_cost=c0, cost=c1, iterations=iters,
                        converged=conv, kinds=kinds, identification=ident)
    if options.restart_change_deg is None:
        return result
    return _restart_suspicious(R_init, batch, result, options, identification_options)
