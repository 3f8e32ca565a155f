"""GRRM: global reprojection residuals on the rotation manifold (paper Alg. 3-4).

For an observation of point k in view i (eq:GRRMRes1, eq:GRRMRes2):

    V_ik = Σ_{e_ij ∈ E_ik} ω_ijk V^{TRRM,i}_{ijk}(R_ij),    ω_ijk = ‖θ_ijk‖ / Σ_j ‖θ_ijk‖   (eq:weight)

i.e. the ‖θ‖-weighted mean of the two-view TRRM residuals that every edge through view i
that matched this observation predicts for it (bearing form, expressed in camera i). Each
edge keeps its own closed-form t_ij(R_ij) (null vector of its Pˢ). An observation is the
pair (view, keypoint): no track building is needed, E_ik is simply the set of edges whose
matches contain that keypoint.

Optimisation (Alg. 4): Levenberg-Marquardt on the 3n rotation parameters with one view
fixed (the gauge), left perturbations R_i <- exp([δ_i]x) R_i. The exact Jacobian is built per
match for the three parameters of R_ij (kernels.trrm_match_terms, including dt/dδ and
dω/dδ), chained to the two cameras with δR_ij = δ_j - R_ij δ_i, and assembled as a scipy
sparse matrix; the normal equations are sparse and solved with SuperLU.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import twoview as tv

log = logging.getLogger("rotonly.grrm")

LOSSES = ("none", "huber", "cauchy")


@dataclass(frozen=True)
class GRRMOptions:
    max_iterations: int = 30  #: k_max of Alg. 4
    function_tolerance: float = 1e-8  #: stop at a relative cost decrease below this (ε of Alg. 4)
    #: stop after an accepted step whose largest rotation update is below this (rad). LM
    #: converges linearly here (measured step ratio ~0.45 per iteration on Strecha), so what
    #: is left is ~0.8 x tol ≈ 1.4e-4 deg, two orders below real rotation errors (~1e-2 deg)
    step_tolerance: float = 3e-6
    initial_damping: float = 1e-4  #: μ relative to diag(JᵀJ)
    max_damping: float = 1e10
    #: robust loss on ‖V_ik‖ (bearing chord units ≈ radians). Real matches contain a few
    #: wrong correspondences that survived two-view RANSAC; "cauchy" bounds their pull.
    loss: str = "cauchy"
    #: loss scale; None = loss_scale_factor x 1.4826 x median ‖V_ik‖ at the start
    loss_scale: float | None = None
    #: 1.5 (a tight Cauchy) was chosen on the three Strecha scenes: their COLMAP inlier sets
    #: hold wrong matches (repeated structure) that a wider loss lets pull the rotations
    #: (mean error, factor 1.5 / 3 / 5: entry 0.0198 / 0.0273 / 0.0587 deg, Herz-Jesus
    #: 0.0176 / 0.0179 / 0.0182, fountain 0.0293 / 0.0289 / 0.0279)
    loss_scale_factor: float = 1.5
    #: first phase on Σ_edges λ_min(Pˢ_ij(R_j R_i^T)) (smooth, like TRRM's first phase):
    #: brings starts a degree or more off into GRRM's basin; 0 disables it
    epipolar_max_iterations: int = 10
    epipolar_step_tolerance: float = 1e-4  #: rad; this phase only has to reach the basin
    #: per-edge t from IRLS-weighted Pˢ (weights fixed at the start; see trrm.TRRMOptions.loss)
    robust_translation: bool = True

    def validate(self) -> "GRRMOptions":
        if self.loss not in LOSSES:
            raise ValueError(f"loss: must be one of {LOSSES}, got {self.loss!r}")
        if self.max_iterations < 0:
            raise ValueError("max_iterations: must be >= 0")
        if self.loss_scale is not None and not self.loss_scale > 0:
            raise ValueError("loss_scale: must be > 0")
        return self


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


class _Problem:
    """The fixed structure of a GRRM problem: edges, matches, observation groups, and the
    sparsity pattern of the normal equations (computed once, refilled every iteration).

    Normal equations without a huge J: J = J_e C, where J_e (3G x 3E) holds one 3x3 block
    B_c per contribution (match side c -> its observation g, derivative w.r.t. its edge's
    δ_e) and C (3E x 3n) chains δ_e = δ_j - R_ij δ_i. Then JᵀJ = Cᵀ (J_eᵀ J_e) C with
    J_eᵀ J_e = Σ_g Σ_{c, c' in g} B_cᵀ B_c' at block (e_c, e_c'): the pairs of contributions
    inside each observation are enumerated once; each iteration only refills the blocks.
    """

    def __init__(self, n: int, edge_views: np.ndarray, batch: tv.EdgeBatch, obs_ids: np.ndarray):
        from rotonly_cli.geometry.tracks import pairs_within_tracks

        self.n = n
        self.E = batch.num_edges
        self.edge_views = edge_views
        self.batch = batch
        self.edge_of_match = np.repeat(np.arange(batch.num_edges), batch.counts)
        self.M = batch.x_i.shape[0]
        # every match contributes to two observations: (view i, its keypoint) and (view j, ...)
        groups, self.group = np.unique(np.concatenate([obs_ids[:, 0], obs_ids[:, 1]]), return_inverse=True)
        self.num_groups = len(groups)
        self.edge_of_contribution = np.concatenate([self.edge_of_match, self.edge_of_match])
        # contributions sorted by observation; pairs (a < b) inside each observation, as
        # positions in that sorted order (so the gathers below stay local in memory)
        self.order = np.argsort(self.group, kind="stable")
        sizes = np.bincount(self.group, minlength=self.num_groups)
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.pair_a, self.pair_b = pairs_within_tracks(offsets)
        edge_sorted = self.edge_of_contribution[self.order]
        self.edge_sorted = edge_sorted
        key = edge_sorted[self.pair_a] * self.E + edge_sorted[self.pair_b]
        self.block_keys, self.pair_block = np.unique(key, return_inverse=True)
        self.block_row = self.block_keys // self.E
        self.block_col = self.block_keys % self.E
        # sums over pairs / contributions as sparse selector products (one C loop each)
        P, K, Nc = len(self.pair_a), len(self.block_keys), len(self.edge_sorted)
        self.pair_selector = sp.csc_matrix((np.ones(P), (self.pair_block, np.arange(P))), shape=(K, P))
        self.diag_selector = sp.csr_matrix((np.ones(Nc), (self.edge_sorted, np.arange(Nc))), shape=(self.E, Nc))

    def relative(self, R: np.ndarray) -> np.ndarray:
        return R[self.edge_views[:, 1]] @ np.swapaxes(R[self.edge_views[:, 0]], 1, 2)

    def evaluate(self, R: np.ndarray, with_jacobian: bool):
        """Per-observation residuals V (G, 3), the weight sums S (G,), and optionally the
        per-contribution Jacobian blocks B (2M, 3, 3) w.r.t. their edge's δ_e."""
        R_ij = self.relative(R)
        terms = kernels.trrm_match_terms(R_ij, self.batch, with_jacobian=with_jacobian)
        R_ij_m = R_ij[self.edge_of_match]  # (M, 3, 3)
        r_i_in_j = terms["r"][:, :3]
        r_i = np.einsum("mba,mb->ma", R_ij_m, r_i_in_j)  # R_ij^T r: view i's residual in camera i
        r_j = terms["r"][:, 3:]
        b = terms["b"] * terms["w"]  # ω numerators (eq:weight); invalid matches weigh 0
        res = np.concatenate([r_i, r_j])  # (2M, 3)
        b2 = np.concatenate([b, b])
        S = np.bincount(self.group, weights=b2, minlength=self.num_groups)
        safe_S = np.where(S > 0, S, 1.0)
        V = np.stack([np.bincount(self.group, weights=b2 * res[:, k], minlength=self.num_groups)
                      for k in range(3)], axis=1) / safe_S[:, None]
        if not with_jacobian:
            return V, S, None
        J = terms["J"]
        db = terms["db"] * terms["w"][:, None]
        # d(R^T v) = R^T (dv + [v]x δ) for R <- exp([δ]x) R
        dr_i = np.einsum("mba,mbc->mac", R_ij_m, J[:, :3, :] + so3.hat(r_i_in_j))
        dres = np.concatenate([dr_i, J[:, 3:, :]])  # (2M, 3, 3)
        db2 = np.concatenate([db, db])
        g = self.group
        # dV_g = Σ_c [(res_c - V_g) db_c^T + b_c dres_c] / S_g   (ω = b / S, eq:weight)
        B = ((res - V[g])[:, :, None] * db2[:, None, :] + b2[:, None, None] * dres) * (1.0 / safe_S)[g][:, None, None]
        return V, S, B

    def chain_matrix(self, R: np.ndarray) -> sp.csr_matrix:
        """C (3E x 3n): δ_e = δ_j - R_ij δ_i."""
        return _chain(R, self.edge_views, self.n)

    def normal_equations(self, R: np.ndarray, V: np.ndarray, B: np.ndarray, row_weight: np.ndarray):
        """(JᵀWJ (3n x 3n, sparse), JᵀW V (3n,)) with per-observation weights W = ρ'."""
        E = self.E
        w_c = row_weight[self.group]
        # J_eᵀ W V per edge: Σ_c B_cᵀ w_g V_g
        BtV = np.einsum("cab,ca->cb", B, V[self.group] * w_c[:, None])
        g_edge = np.stack([np.bincount(self.edge_of_contribution, weights=BtV[:, k], minlength=E)
                           for k in range(3)], axis=1).ravel()
        Bs = B[self.order].reshape(-1, 9)
        wBs = Bs * w_c[self.order][:, None]

        def products(Ba, Bb):  # per pair B_aᵀ B_b, flattened (P, 9)
            return np.einsum("pka,pkb->pab", Ba.reshape(-1, 3, 3), Bb.reshape(-1, 3, 3)).reshape(-1, 9)

        # diagonal pairs (c, c): blocks (e_c, e_c)
        diag = np.asarray(self.diag_selector @ products(wBs, Bs)).reshape(E, 3, 3)
        # pairs c < c' inside one observation: blocks (e_c, e_c') and their transposes
        K = len(self.block_keys)
        off = np.zeros((K, 9))
        step = 1 << 18
        for p0 in range(0, len(self.pair_a), step):
            pa = self.pair_a[p0:p0 + step]
            pb = self.pair_b[p0:p0 + step]
            off += self.pair_selector[:, p0:p0 + len(pa)] @ products(wBs[pa], Bs[pb])
        off = off.reshape(K, 3, 3)
        rows = np.concatenate([np.arange(E), self.block_row, self.block_col])
        cols = np.concatenate([np.arange(E), self.block_col, self.block_row])
        data = np.concatenate([diag, off, np.swapaxes(off, 1, 2)])
        H = sp.bsr_matrix((data, cols, np.arange(len(rows) + 1)), shape=(3 * len(rows), 3 * E))
        # rows of that BSR are one per block: sum them into block row r via a selector
        Sel = sp.csr_matrix((np.ones(len(rows)), (rows, np.arange(len(rows)))), shape=(E, len(rows)))
        H = sp.kron(Sel, sp.identity(3), format="csr") @ H
        C = self.chain_matrix(R)
        return (C.T @ H @ C).tocsc(), C.T @ g_edge


def _robust(sq_norm: np.ndarray, loss: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """ρ(s) and ρ'(s) of a squared norm s (Ceres' convention: ρ(s) ≈ s near 0)."""
    if loss == "none":
        return sq_norm, np.ones_like(sq_norm)
    c2 = scale * scale
    if loss == "huber":
        small = sq_norm <= c2
        root = np.sqrt(sq_norm)
        rho = np.where(small, sq_norm, 2.0 * scale * root - c2)
        drho = np.where(small, 1.0, scale / np.where(small, 1.0, root))
        return rho, drho
    rho = c2 * np.log1p(sq_norm / c2)  # cauchy
    drho = 1.0 / (1.0 + sq_norm / c2)
    return rho, drho


def validate_inputs(R_cam_from_world, edge_views, batch: tv.EdgeBatch, obs_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R = tv.as_rotations(R_cam_from_world, "R_cam_from_world").reshape(-1, 3, 3).astype(float)
    n = R.shape[0]
    edge_views = np.asarray(edge_views)
    if edge_views.ndim != 2 or edge_views.shape[1] != 2 or edge_views.shape[0] != batch.num_edges:
        raise ValueError(f"edge_views: expected shape ({batch.num_edges}, 2), got {edge_views.shape}")
    if not np.issubdtype(edge_views.dtype, np.integer):
        raise ValueError("edge_views: must be integer view indices")
    if edge_views.size and (edge_views.min() < 0 or edge_views.max() >= n or np.any(edge_views[:, 0] == edge_views[:, 1])):
        raise ValueError(f"edge_views: view indices must be distinct and in [0, {n})")
    obs_ids = np.asarray(obs_ids)
    if obs_ids.shape != (batch.x_i.shape[0], 2) or not np.issubdtype(obs_ids.dtype, np.integer):
        raise ValueError(f"obs_ids: expected an integer array of shape ({batch.x_i.shape[0]}, 2), got {obs_ids.shape}")
    return R, edge_views.astype(np.int64), obs_ids.astype(np.int64)


def _chain(R: np.ndarray, edge_views: np.ndarray, n: int) -> sp.csr_matrix:
    """C (3E x 3n): δ_e = δ_j - R_ij δ_i for left perturbations of both cameras."""
    R_ij = R[edge_views[:, 1]] @ np.swapaxes(R[edge_views[:, 0]], 1, 2)
    E = len(edge_views)
    rows = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, :, None], (E, 3, 3)).ravel()
    cols_j = np.broadcast_to((3 * edge_views[:, 1])[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    cols_i = np.broadcast_to((3 * edge_views[:, 0])[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    data = np.concatenate([np.broadcast_to(np.eye(3), (E, 3, 3)).ravel(), (-R_ij).ravel()])
    return sp.csr_matrix((data, (np.concatenate([rows, rows]), np.concatenate([cols_j, cols_i]))), shape=(3 * E, 3 * n))


def _block_diag(blocks: np.ndarray) -> sp.csr_matrix:
    E = len(blocks)
    rows = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, :, None], (E, 3, 3)).ravel()
    cols = np.broadcast_to((3 * np.arange(E))[:, None, None] + np.arange(3)[None, None, :], (E, 3, 3)).ravel()
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * E, 3 * E))


def _solve_damped(JtJ, grad, mu):
    diag = JtJ.diagonal()
    diag = np.where(diag > 0, diag, 1.0)
    try:
        delta = -spla.spsolve((JtJ + sp.diags(mu * diag)).tocsc(), grad)
    except RuntimeError:
        return None
    return delta if np.all(np.isfinite(delta)) else None


def epipolar_phase(R: np.ndarray, edge_views: np.ndarray, batch: tv.EdgeBatch, free: np.ndarray,
                   max_iterations: int, step_tolerance: float) -> tuple[np.ndarray, int]:
    """LM on Σ_e λ_min(Pˢ_e(R_j R_i^T)) (bearing-normalised θ): per-edge normal equations
    from kernels.epipolar_normal_equations chained to the cameras, JᵀJ = Cᵀ diag(JᵀJ_e) C."""
    n = R.shape[0]
    R_ij = R[edge_views[:, 1]] @ np.swapaxes(R[edge_views[:, 0]], 1, 2)
    ev = kernels.epipolar_normal_equations(R_ij, batch)
    cost = float(ev.cost.sum())
    mu = 1e-4
    it = 0
    for it in range(1, max_iterations + 1):
        C = _chain(R, edge_views, n)
        JtJ = (C.T @ _block_diag(ev.JtJ) @ C).tocsc()[free][:, free]
        grad = (C.T @ ev.Jtr.ravel())[free]
        while True:
            delta_free = _solve_damped(JtJ, grad, mu)
            if delta_free is not None:
                delta = np.zeros(3 * n)
                delta[free] = delta_free
                R_cand = so3.exp(delta.reshape(n, 3)) @ R
                R_ij = R_cand[edge_views[:, 1]] @ np.swapaxes(R_cand[edge_views[:, 0]], 1, 2)
                ev_c = kernels.epipolar_normal_equations(R_ij, batch)
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


def optimize_global_rotations(R_cam_from_world, edge_views, batch: tv.EdgeBatch, obs_ids, fixed_view: int = 0,
                              options: GRRMOptions = GRRMOptions()) -> GRRMResult:
    """Alg. 4: minimise Σ_ik ρ(‖V_ik‖²) (eq:GRRMerror) over the rotations, one view fixed."""
    options.validate()
    R, edge_views, obs_ids = validate_inputs(R_cam_from_world, edge_views, batch, obs_ids)
    n = R.shape[0]
    if not 0 <= fixed_view < n:
        raise ValueError(f"fixed_view: must be in [0, {n})")
    problem = _Problem(n, edge_views, batch, obs_ids)
    free = np.ones(3 * n, dtype=bool)
    free[3 * fixed_view:3 * fixed_view + 3] = False
    R_input = R
    V, S, B = problem.evaluate(R, with_jacobian=True)
    sq = np.einsum("gk,gk->g", V, V)
    scale = options.loss_scale
    if scale is None:
        active = S > 0
        med = np.median(np.sqrt(sq[active])) if np.any(active) else 0.0
        scale = max(options.loss_scale_factor * 1.4826 * med, 1e-12)
    rho, drho = _robust(sq, options.loss, scale)
    cost = float(rho.sum())
    if options.epipolar_max_iterations > 0 and batch.num_edges:
        # the λ_min phase only proposes a start: keep it if GRRM's own cost agrees it is
        # better (on weak geometry, e.g. far points, λ_min's optimum can be worse)
        R1, it1 = epipolar_phase(R, edge_views, batch, free, options.epipolar_max_iterations,
                                 options.epipolar_step_tolerance)
        V1, S1, B1 = problem.evaluate(R1, with_jacobian=True)
        sq1 = np.einsum("gk,gk->g", V1, V1)
        rho1, drho1 = _robust(sq1, options.loss, scale)
        if float(rho1.sum()) < cost:
            R, V, S, B, sq, rho, drho, cost = R1, V1, S1, B1, sq1, rho1, drho1, float(rho1.sum())
        log.info("GRRM λ_min phase: %d iterations, start %s", it1, "taken" if R is R1 else "kept")
    if options.robust_translation and batch.num_edges:
        # each edge's t from Σ w θθᵀ with Huber IRLS weights of its matches (weight 1 within
        # 3 robust sigmas, so clean data is untouched): wrong matches with large θ would
        # otherwise tilt t for the whole edge. Weighed at the chosen start, after the λ_min
        # phase (weights from a start far off would down-weight good matches).
        from rotonly_cli.geometry.trrm import TRRMOptions, robust_match_weights

        R_ij = R[edge_views[:, 1]] @ np.swapaxes(R[edge_views[:, 0]], 1, 2)
        w = robust_match_weights(R_ij, batch, None, TRRMOptions(), kind="huber")
        w = robust_match_weights(R_ij, batch, w, TRRMOptions(), kind="huber")
        problem.batch = batch.with_weights(w)
        V, S, B = problem.evaluate(R, with_jacobian=True)
        sq = np.einsum("gk,gk->g", V, V)
        rho, drho = _robust(sq, options.loss, scale)
        cost = float(rho.sum())
    # the initial cost of the problem that is optimised (same weights and scale as the end)
    V0, _, _ = problem.evaluate(R_input, with_jacobian=False)
    initial_cost = float(_robust(np.einsum("gk,gk->g", V0, V0), options.loss, scale)[0].sum())
    history: list[dict] = []
    mu = options.initial_damping
    converged = False
    iteration = 0
    log.info("GRRM start: %d views, %d edges, %d observations, cost %.6e, loss %s (scale %.3e)",
             n, batch.num_edges, problem.num_groups, cost, options.loss, scale)
    for iteration in range(1, options.max_iterations + 1):
        t0 = time.perf_counter()
        # IRLS form of the robust loss: observation weights ρ'(s)
        JtJ, grad = problem.normal_equations(R, V, B, drho)
        JtJ = JtJ[free][:, free]
        grad = grad[free]
        accepted = False
        while True:
            delta_free = _solve_damped(JtJ, grad, mu)
            if delta_free is None:
                mu *= 10.0
                if mu > options.max_damping:
                    break
                continue
            delta = np.zeros(3 * n)
            delta[free] = delta_free
            R_cand = so3.exp(delta.reshape(n, 3)) @ R
            # evaluate the candidate with its Jacobian: accepted steps (the usual case) reuse it
            V_c, S_c, B_c = problem.evaluate(R_cand, with_jacobian=True)
            sq_c = np.einsum("gk,gk->g", V_c, V_c)
            rho_c, drho_c = _robust(sq_c, options.loss, scale)
            cost_c = float(rho_c.sum())
            step = float(np.max(np.linalg.norm(delta.reshape(n, 3), axis=1)))
            if cost_c <= cost:
                accepted = True
                break
            mu *= 10.0
            if mu > options.max_damping:
                break
        if not accepted:
            history.append({"iteration": iteration, "cost": cost, "step": 0.0, "damping": mu, "accepted": False,
                            "seconds": time.perf_counter() - t0})
            log.info("GRRM iteration %d: no decrease possible (damping %.1e); stop", iteration, mu)
            converged = True
            break
        decrease = cost - cost_c
        R, V, S, B, sq, rho, drho, cost = R_cand, V_c, S_c, B_c, sq_c, rho_c, drho_c, cost_c
        mu = max(mu / 10.0, 1e-15)
        history.append({"iteration": iteration, "cost": cost, "step": step, "damping": mu, "accepted": True,
                        "seconds": time.perf_counter() - t0})
        log.info("GRRM iteration %d: cost %.6e (-%.2e), max step %.2e rad, %.2f s",
                 iteration, cost, decrease, step, time.perf_counter() - t0)
        if decrease <= options.function_tolerance * max(cost, 1e-300) or step < options.step_tolerance:
            converged = True
            break
    return GRRMResult(R_cam_from_world=R, initial_cost=initial_cost, cost=cost, iterations=iteration,
                      converged=converged, history=history, num_observations=problem.num_groups, loss_scale=scale)


def grrm_residuals(R_cam_from_world, edge_views, batch: tv.EdgeBatch, obs_ids, with_jacobian: bool = False):
    """V_ik (G, 3) of eq:GRRMRes2 for every observation (order: sorted unique ids) and,
    optionally, the explicit sparse Jacobian J = J_e C (3G x 3n, left perturbations of the
    cameras) — for tests and small problems; the optimiser never forms it."""
    R, edge_views, obs_ids = validate_inputs(R_cam_from_world, edge_views, batch, obs_ids)
    problem = _Problem(R.shape[0], edge_views, batch, obs_ids)
    V, _, B = problem.evaluate(R, with_jacobian)
    if not with_jacobian:
        return V, None
    nc = len(B)
    rows = (3 * problem.group)[:, None, None] + np.arange(3)[None, :, None]
    cols = (3 * problem.edge_of_contribution)[:, None, None] + np.arange(3)[None, None, :]
    J_e = sp.csr_matrix((B.ravel(), (np.broadcast_to(rows, (nc, 3, 3)).ravel(), np.broadcast_to(cols, (nc, 3, 3)).ravel())),
                        shape=(3 * problem.num_groups, 3 * problem.E))
    return V, (J_e @ problem.chain_matrix(R)).tocsr()
