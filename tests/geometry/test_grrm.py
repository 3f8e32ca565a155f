"""GRRM (paper Alg. 3-4): residual definition, exact Jacobian, normal equations, exact
recovery, and accuracy against its robust-averaging start on the paper's set-ups."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from rotonly_cli import multiview
from rotonly_cli.geometry import alignment, grrm, so3

from helpers import DyingPeer
from helpers import grrm_problem as _problem
from helpers import l1_irls_start as _l1_irls_start


def _mean_err_deg(R, R_gt):
    return float(alignment.rotation_errors_after_alignment(R, R_gt)[0].mean())


@pytest.mark.parametrize("residual", ["bearing", "image"])
def test_residual_is_weighted_mean_of_two_view_residuals(residual):
    """eq:GRRMRes2 for one observation seen by three views, computed by hand from TRRM: the
    ‖θ‖-weighted mean of the bearing residuals x̂ - ŝ, or of the image-plane residuals
    x/x_z - ŝ/ŝ_z (eq:GRRMRes1: reprojection X^i_ijk = Y/Y_3, eq:PA2)."""
    from rotonly_cli.geometry import pairwise as pg

    p, prob, R_gt = _problem(noise=1.0, seed=3, views=6, window=2)
    R = so3.exp(np.random.default_rng(0).normal(scale=0.003, size=(6, 3))) @ R_gt
    V, _ = grrm.grrm_residuals(R, prob.edge_views, prob.batch, prob.obs_ids, residual=residual)
    ids = np.unique(np.concatenate([prob.obs_ids[:, 0], prob.obs_ids[:, 1]]))
    # pick an observation that belongs to at least two edges
    counts = np.bincount(np.searchsorted(ids, np.concatenate([prob.obs_ids[:, 0], prob.obs_ids[:, 1]])))
    g = int(np.flatnonzero(counts >= 2)[0])
    obs = ids[g]
    num, den = np.zeros(3), 0.0
    offsets = prob.batch.offsets
    for e, (vi, vj) in enumerate(prob.edge_views):
        R_ij = R[vj] @ R[vi].T
        sub = prob.batch.subset(np.array([e]))
        ev = pg.trrm_residuals(R_ij[None], sub)
        theta = pg.theta_vectors(R_ij[None], sub)
        for k in range(offsets[e], offsets[e + 1]):
            for side in (0, 1):
                if prob.obs_ids[k, side] != obs:
                    continue
                row = k - offsets[e]
                w = np.linalg.norm(theta[row])  # ω numerator, eq:weight
                r = R_ij.T @ ev.residuals[row, :3] if side == 0 else ev.residuals[row, 3:]
                if residual == "image":
                    x = (sub.x_i if side == 0 else sub.x_j)[row]
                    s_hat = x / np.linalg.norm(x) - r  # the reprojection's bearing
                    r = x / x[2] - s_hat / s_hat[2]
                    assert r[2] == 0.0
                num += w * r
                den += w
    assert den > 0
    np.testing.assert_allclose(V[g], num / den, atol=1e-14)


@pytest.mark.parametrize("residual", ["bearing", "image"])
def test_jacobian_matches_central_differences(residual):
    p, prob, R_gt = _problem(noise=2.0, seed=4, views=6, window=2)
    R = so3.exp(np.random.default_rng(1).normal(scale=0.005, size=(6, 3))) @ R_gt

    def residuals(R_at, with_jacobian=False):
        return grrm.grrm_residuals(R_at, prob.edge_views, prob.batch, prob.obs_ids, with_jacobian=with_jacobian,
                                   residual=residual)

    V, J = residuals(R, True)
    J = J.toarray()
    h = 1e-6
    J_fd = np.zeros_like(J)
    for col in range(3 * len(R)):
        d = np.zeros((len(R), 3))
        d.flat[col] = h
        J_fd[:, col] = (residuals(so3.exp(d) @ R)[0] - residuals(so3.exp(-d) @ R)[0]).ravel() / (2 * h)
    assert np.max(np.abs(J - J_fd)) / np.max(np.abs(J)) < 1e-6


@pytest.mark.parametrize("chunk", [1 << 15, 97])
def test_normal_equations_equal_explicit_jacobian_products(chunk, monkeypatch):
    """Also with blocks of 97 contributions: block edges fall on observation boundaries and
    the pairs of every observation stay inside one block."""
    monkeypatch.setattr(grrm.problem, "_CHUNK", chunk)
    p, prob, R_gt = _problem(noise=1.0, seed=5, views=8, window=3)
    R = so3.exp(np.random.default_rng(2).normal(scale=0.003, size=(8, 3))) @ R_gt
    problem = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids)
    V, _, B = problem.evaluate(R, with_jacobian=True)
    w = np.random.default_rng(3).uniform(0.2, 1.0, len(V))
    A, g = problem.normal_equations(R, V, B, w)
    _, J = grrm.grrm_residuals(R, prob.edge_views, prob.batch, prob.obs_ids, with_jacobian=True)
    W = sp.diags(np.repeat(w, 3))
    A_ref = (J.T @ W @ J).toarray()
    g_ref = J.T @ (np.repeat(w, 3) * V.ravel())
    assert np.max(np.abs(A.toarray() - A_ref)) <= 1e-12 * np.abs(A_ref).max()
    assert np.max(np.abs(g - g_ref)) <= 1e-12 * np.abs(g_ref).max()


@pytest.mark.parametrize("residual", ["bearing", "image"])
def test_cost_alone_equals_cost_with_normal_equations(residual):
    """LM judges a retried candidate by the cost alone and linearises it only once accepted:
    the two costs must be the same number, or a step could be accepted on one and the run
    continue from the other."""
    p, prob, R_gt = _problem(noise=1.0, seed=5, views=8, window=3)
    problem = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids, residual)
    rng = np.random.default_rng(4)
    for _ in range(3):
        R = so3.exp(rng.normal(scale=0.01, size=(8, 3))) @ R_gt
        alone = problem.linearize(R, "geman_mcclure", 1e-3, True, False)
        full = problem.linearize(R, "geman_mcclure", 1e-3, True, True, True)
        assert alone[1] is None and full[1] is not None
        assert alone[0] == full[0]


def test_robust_hessian_same_optimum_fewer_iterations():
    """The loss's second-order term (Triggs' correction) changes the steps, not the minimum."""
    p, prob, R_gt = _problem("circular", noise=2.0, seed=9, views=10, window=3)
    R0 = _l1_irls_start(p, prob)
    tight = dict(step_tolerance=1e-10, function_tolerance=0.0, max_iterations=100)
    plain = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                           options=grrm.GRRMOptions(robust_hessian=False, **tight))
    second = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                            options=grrm.GRRMOptions(robust_hessian=True, **tight))
    assert np.max(so3.geodesic_angle(plain.R_cam_from_world, second.R_cam_from_world)) < 1e-8
    assert abs(plain.cost - second.cost) <= 1e-10 * plain.cost
    assert second.iterations < plain.iterations, (second.iterations, plain.iterations)


@pytest.mark.parametrize("setup", ["circular", "linear"])
def test_noise_free_exact_recovery(setup):
    p, prob, R_gt = _problem(setup, noise=0.0, seed=2, views=8, window=3, init="truth")
    R0 = so3.exp(np.random.default_rng(4).normal(scale=np.deg2rad(1.0), size=(8, 3))) @ R_gt
    R0[0] = R_gt[0]  # the gauge view
    res = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids, fixed_view=0,
                                         options=grrm.GRRMOptions(loss="none", step_tolerance=1e-12,
                                                                  function_tolerance=0.0))
    assert np.max(so3.geodesic_angle(res.R_cam_from_world, R_gt)) < 1e-8
    assert res.cost < 1e-20


@pytest.mark.parametrize("setup", ["circular", "square", "linear", "outward"])
def test_grrm_beats_its_l1_irls_start(setup):
    """≥ 90 % of 30 seeded trials per set-up (5-point RANSAC pairs, 1 px)."""
    wins = 0
    # outward-looking rings see far points with little parallax: more points keep the graph connected
    views, points = (12, 1500) if setup == "outward" else (10, 400)
    for seed in range(30):
        p, prob, R_gt = _problem(setup, noise=1.0, seed=100 + seed, views=views, points=points, window=3)
        R0 = _l1_irls_start(p, prob)
        res = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids)
        wins += _mean_err_deg(res.R_cam_from_world, R_gt) < _mean_err_deg(R0, R_gt)
    assert wins >= 27, wins


def test_corrupted_edges_do_not_spoil_the_result():
    """20 % of the pairs' relative rotations replaced by random rotations (repeated structure):
    robust averaging + GRRM stays within 1.5x of the uncorrupted run."""
    errs = []
    for corrupt in (0.0, 0.2):
        p, prob, R_gt = _problem("circular", noise=1.0, seed=7, views=16, points=800, window=4, corrupt=corrupt)
        R0 = _l1_irls_start(p, prob)
        res = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids)
        errs.append(_mean_err_deg(res.R_cam_from_world, R_gt))
    assert errs[1] <= 1.5 * errs[0]


def test_public_api_and_bad_input():
    p, prob, R_gt = _problem(noise=1.0, seed=8, views=6, window=2, init="perturbed")
    sc = p.scene
    vids = sorted(sc.views)
    rotations = {v: R_gt[k] @ so3.exp(np.array([0.0, 0.002 * k, 0.0])) for k, v in enumerate(vids)}
    edges = {k: sc.pairs[k].matches for k in sorted(sc.pairs)}
    out = multiview.optimize_rotations(rotations, sc.normalized, edges)
    assert set(out.rotations) == set(vids)
    assert out.cost < out.initial_cost
    with pytest.raises(ValueError, match="R_cam_from_world"):
        grrm.optimize_global_rotations(np.ones((6, 3, 3)), prob.edge_views, prob.batch, prob.obs_ids)
    with pytest.raises(ValueError, match="edge_views"):
        grrm.optimize_global_rotations(R_gt, prob.edge_views[:-1], prob.batch, prob.obs_ids)
    with pytest.raises(ValueError, match="obs_ids"):
        grrm.optimize_global_rotations(R_gt, prob.edge_views, prob.batch, prob.obs_ids[:-1])
    with pytest.raises(ValueError, match="loss"):
        grrm.GRRMOptions(loss="tukey").validate()


def test_linearisation_in_two_processes_equals_one_process_bit_for_bit(monkeypatch):
    """GRRMSystem.parallel: the forked child evaluates the second share of the parts (their
    match tables and sums); cost, JᵀWJ, JᵀWV and the remainder are the same bits as in one
    process, also after the batch's weights change (the child gets the new batch)."""
    from rotonly_cli.runtime import parallel

    monkeypatch.setattr(grrm.problem, "_CHUNK", 301)  # several blocks per part
    p, prob, R_gt = _problem(noise=1.0, seed=5, views=8, window=3)
    R = so3.exp(np.random.default_rng(2).normal(scale=0.003, size=(8, 3))) @ R_gt
    weights = np.random.default_rng(3).uniform(0.5, 1.0, prob.batch.x_i.shape[0])

    def evaluations(problem):
        out = []
        for batch in (prob.batch, prob.batch.with_weights(weights)):
            problem.batch = batch
            out.append(problem.linearize(R, "geman_mcclure", 1e-4, True, True, True))
            out.append(problem.linearize(R, "geman_mcclure", 1e-4, True, False))
        return out

    one = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids)
    assert len(one.shares) == 2
    serial = evaluations(one)
    two = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids)
    with two.parallel(parallel.ForkedPeer):
        assert two.processes == 2
        forked = evaluations(two)
    assert serial[0][3] is not None  # the remainder is compared too
    for a, b in zip(serial, forked):
        assert a[0] == b[0]
        for x, y in zip(a[1:], b[1:]):
            assert (x is None and y is None) or np.array_equal(x, y)
    with one.parallel(None):
        assert one.processes == 1


def test_a_helper_process_leaves_grrm_unchanged_bit_for_bit():
    from rotonly_cli.runtime import parallel

    p, prob, R_gt = _problem("circular", noise=1.0, seed=9, views=10, window=3)
    R0 = _l1_irls_start(p, prob)
    one = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids)
    two = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                         peer_class=parallel.ForkedPeer)
    assert (one.processes, two.processes) == (1, 2)
    assert np.array_equal(one.R_cam_from_world, two.R_cam_from_world)
    assert one.cost == two.cost and one.iterations == two.iterations
    # a helper that dies at its first request: this process takes its part over, same bits
    dead = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids, peer_class=DyingPeer)
    assert np.array_equal(one.R_cam_from_world, dead.R_cam_from_world) and one.cost == dead.cost


def test_translation_weights_in_halves_equal_the_whole_and_a_helper_computes_the_same_bits():
    """GRRM's per-match translation weights are computed in two halves of the edges (the
    second in the helper process, if there is one): the same weights as one pass over all the
    edges, and the same bits with or without the helper."""
    from rotonly_cli.runtime import parallel

    p, prob, R_gt = _problem(noise=1.0, seed=4, views=8, window=3)
    R = so3.exp(np.random.default_rng(5).normal(scale=0.003, size=(8, 3))) @ R_gt
    system = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids)
    assert 0 < system._weights_split < system.E
    whole = grrm.problem.translation_weights(system.relative(R), prob.batch)
    halves = system.translation_weights(R, prob.batch)
    assert halves.shape == (prob.batch.x_i.shape[0],) and np.all(halves > 0) and np.any(halves < 1)
    np.testing.assert_allclose(halves, whole, rtol=1e-12, atol=1e-15)
    with system.parallel(parallel.ForkedPeer):
        assert system.processes == 2
        assert np.array_equal(system.translation_weights(R, prob.batch), halves)


def test_a_failed_exact_step_is_retried_from_the_psd_model_at_the_same_damping(monkeypatch):
    """When the step of the exact Hessian (JᵀWJ minus the remainder) raises the cost, LM tries
    the clamped PSD model at the same damping before it damps more. Simulated: every exact
    step is made to overshoot (x 40)."""
    from rotonly_cli.geometry.grrm import solve

    solves = []
    damped = solve._solve_damped

    def overshooting(JtJ, grad, mu, remainder=None):
        delta = damped(JtJ, grad, mu, remainder)
        solves.append((mu, remainder is not None))
        return None if delta is None else (40.0 * delta if remainder is not None else delta)

    monkeypatch.setattr(solve, "_solve_damped", overshooting)
    p, prob, R_gt = _problem("circular", noise=1.0, seed=9, views=10, window=3)
    R0 = _l1_irls_start(p, prob)
    tight = dict(step_tolerance=1e-10, function_tolerance=0.0, max_iterations=100, epipolar_max_iterations=0)
    options = grrm.GRRMOptions(exact_curvature_below=np.inf, **tight)
    result = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids, options=options)
    exact_then_psd = [k for k in range(len(solves) - 1) if solves[k][1] and not solves[k + 1][1]]
    assert exact_then_psd  # the exact steps failed and were retried ...
    assert all(solves[k + 1][0] == solves[k][0] for k in exact_then_psd)  # ... at the same damping
    monkeypatch.setattr(solve, "_solve_damped", damped)
    plain = grrm.optimize_global_rotations(R0, prob.edge_views, prob.batch, prob.obs_ids,
                                           options=grrm.GRRMOptions(robust_hessian=False, **tight))
    assert np.max(so3.geodesic_angle(result.R_cam_from_world, plain.R_cam_from_world)) < 1e-8


def test_stops_at_the_relative_cost_decrease_and_damping_keeps_the_optimum():
    """function_tolerance: LM stops after the first accepted step whose cost decrease is below
    that fraction of the cost (the tight run's history tells where); initial_damping changes
    the path, not the optimum."""
    p, prob, R_gt = _problem("circular", noise=1.0, seed=9, views=10, window=3)
    R0 = _l1_irls_start(p, prob)
    args = (R0, prob.edge_views, prob.batch, prob.obs_ids)
    tight = dict(step_tolerance=0.0, function_tolerance=0.0, max_iterations=6, epipolar_max_iterations=0)
    full = grrm.optimize_global_rotations(*args, options=grrm.GRRMOptions(**tight))
    costs = [full.initial_cost] + [h["cost"] for h in full.history]
    relative = [(a - b) / b for a, b in zip(costs[:-1], costs[1:])]
    assert len(relative) >= 3 and relative[1] > relative[2] > 0
    cut = dict(tight, function_tolerance=float(np.sqrt(relative[1] * relative[2])))
    stopped = grrm.optimize_global_rotations(*args, options=grrm.GRRMOptions(**cut))
    assert stopped.iterations == 3 and stopped.converged and stopped.cost == full.history[2]["cost"]
    ends = [grrm.optimize_global_rotations(*args, options=grrm.GRRMOptions(
        initial_damping=mu, step_tolerance=1e-10, function_tolerance=0.0, max_iterations=100)) for mu in (1e-4, 1e-8)]
    assert np.max(so3.geodesic_angle(ends[0].R_cam_from_world, ends[1].R_cam_from_world)) < 1e-8
