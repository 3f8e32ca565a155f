"""GRRM speed paths (issue 5 time target): the fused linearisation, the dense view-block
assembly, the exact radial curvature remainder, and the λ_min phase trigger, each checked
against the explicit Jacobian or against the flow they replace."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import scipy.sparse as sp

from rotonly_cli.geometry import grrm, robust, so3

from helpers import grrm_problem as _problem
from helpers import l1_irls_start as _l1_irls_start


@pytest.fixture(scope="module")
def setup():
    p, prob, R_gt = _problem(seed=5, views=8)
    R = so3.exp(np.random.default_rng(2).normal(scale=0.003, size=(8, 3))) @ R_gt
    V, J = grrm.grrm_residuals(R, prob.edge_views, prob.batch, prob.obs_ids, with_jacobian=True)
    sq = np.einsum("gk,gk->g", V, V)
    scale = float(1.5 * 1.4826 * np.median(np.sqrt(sq)))  # ~25 % of the observations beyond it
    return p, prob, R, V, J, sq, scale


@pytest.mark.parametrize("chunk", [1 << 15, 97])
@pytest.mark.parametrize("dense", [True, False])
@pytest.mark.parametrize("loss", ["cauchy", "geman_mcclure"])
@pytest.mark.parametrize("parts", ["two", "many"])
def test_linearize_equals_explicit_jacobian(setup, chunk, dense, loss, parts, monkeypatch):
    """Cost, JᵀWJ (with Triggs' clamped radial term), JᵀWV and the exact-curvature remainder
    from the block-by-block linearisation equal the products of the explicit Jacobian, for the
    dense and the sparse view-block assembly, blocks cut every 97 contributions, and ("many")
    parts of ~300 incident matches (edges between parts computed in both) with the pair blocks
    addressed through the table of the blocks that occur (layout.DENSE_PAIR_BLOCKS exceeded)."""
    monkeypatch.setattr(grrm.problem, "_CHUNK", chunk)
    monkeypatch.setattr(grrm.problem, "_DENSE_MAX_VIEWS", 200 if dense else 0)
    if parts == "many":
        monkeypatch.setattr(grrm.layout, "PART_MATCHES", 300)
        monkeypatch.setattr(grrm.layout, "DENSE_PAIR_BLOCKS", 0)
    p, prob, R, V, J, sq, scale = setup
    problem = grrm.GRRMSystem(8, prob.edge_views, prob.batch, prob.obs_ids)
    assert (len(problem.layout.parts) > 4) == (parts == "many")
    cost, H, g, remainder = problem.linearize(R, loss, scale, True, True, exact_radial_curvature=True)
    assert isinstance(H, np.ndarray) == dense
    rho, drho = robust.robust_rho(sq, loss, scale)
    beta = robust.robust_curvature(sq, loss, scale)
    u = sq / scale**2
    excess = np.maximum((4 if loss == "geman_mcclure" else 2) * u / (1 + u) - 1, 0)
    assert 0.05 < np.mean(excess > 0) < 0.5  # the remainder is really exercised
    v_hat = V / np.sqrt(sq)[:, None]
    # per observation: ρ' (I - β v̂v̂ᵀ) and the remainder's ρ' (β_exact - 1)₊ v̂v̂ᵀ as 3x3 blocks
    W_blocks = drho[:, None, None] * (np.eye(3) - beta[:, None, None] * v_hat[:, :, None] * v_hat[:, None, :])
    X_blocks = (drho * excess)[:, None, None] * v_hat[:, :, None] * v_hat[:, None, :]
    W = sp.block_diag(list(W_blocks), format="csr")
    X = sp.block_diag(list(X_blocks), format="csr")
    H_ref = (J.T @ W @ J).toarray()
    X_ref = (J.T @ X @ J).toarray()
    g_ref = J.T @ (np.repeat(drho, 3) * V.ravel())
    H_dense = H if dense else H.toarray()
    rem_dense = remainder if dense else remainder.toarray()
    assert abs(cost - rho.sum()) <= 1e-12 * rho.sum()
    assert np.max(np.abs(H_dense - H_ref)) <= 1e-12 * np.abs(H_ref).max()
    assert np.max(np.abs(rem_dense - X_ref)) <= 1e-12 * np.abs(X_ref).max()
    assert np.max(np.abs(g - g_ref)) <= 1e-12 * np.abs(g_ref).max()
    # without the Jacobian: the cost only
    cost_only = problem.linearize(R, loss, scale, True, False)
    assert cost_only[1:] == (None, None, None) and abs(cost_only[0] - cost) <= 1e-13 * cost


def test_exact_radial_curvature_same_optimum_fewer_iterations():
    """The exact Cauchy Hessian (exact_curvature_below, off by default) changes the steps, not
    the minimum, and needs no more iterations than the clamped one to a tight tolerance."""
    p, prob, R_gt = _problem(seed=9, views=10, noise=2.0)
    R0 = _l1_irls_start(p, prob)
    tight = dict(step_tolerance=1e-10, function_tolerance=0.0, max_iterations=100)
    args = (R0, prob.edge_views, prob.batch, prob.obs_ids)
    clamped = grrm.optimize_global_rotations(*args, options=grrm.GRRMOptions(exact_curvature_below=0.0, **tight))
    exact = grrm.optimize_global_rotations(*args, options=grrm.GRRMOptions(exact_curvature_below=1e-3, **tight))
    assert np.max(so3.geodesic_angle(clamped.R_cam_from_world, exact.R_cam_from_world)) < 1e-8
    assert abs(clamped.cost - exact.cost) <= 1e-10 * clamped.cost
    assert exact.iterations <= clamped.iterations, (exact.iterations, clamped.iterations)
    # at the default step tolerance the two also agree to far below real rotation errors
    default = grrm.optimize_global_rotations(*args)
    assert np.degrees(np.max(so3.geodesic_angle(default.R_cam_from_world, exact.R_cam_from_world))) < 1e-4


def _grrm_log(caplog, *args, **kw):
    caplog.clear()
    with caplog.at_level(logging.DEBUG, logger="rotonly.grrm"):
        res = grrm.optimize_global_rotations(*args, **kw)
    phase = [r.getMessage() for r in caplog.records if "λ_min phase:" in r.getMessage()]
    assert len(phase) == 1
    return res, phase[0]


def test_epipolar_trigger_skips_the_phase_only_near_the_optimum(caplog):
    """Start 0.05 deg off: GRRM's first step is small, the λ_min phase is skipped, and the
    result equals the flow that always runs it first (epipolar_trigger=None) when that flow
    keeps the start. Start 3 deg off: the first step exceeds the trigger and the phase runs,
    exactly as with epipolar_trigger=None. (Cauchy loss: its first step from near the optimum
    is a plain Gauss-Newton step; Geman-McClure's may need damping, which runs the phase.)"""
    p, prob, R_gt = _problem(seed=11, views=8, noise=1.0)
    args = (prob.edge_views, prob.batch, prob.obs_ids)
    rng = np.random.default_rng(7)
    near = so3.exp(rng.normal(scale=np.deg2rad(0.05), size=(8, 3))) @ R_gt
    cauchy = grrm.GRRMOptions(loss="cauchy")
    res, msg = _grrm_log(caplog, near, *args, options=cauchy)
    assert "skipped" in msg
    ref, ref_msg = _grrm_log(caplog, near, *args, options=grrm.GRRMOptions(loss="cauchy", epipolar_trigger=None))
    if "kept" in ref_msg:
        assert np.max(so3.geodesic_angle(res.R_cam_from_world, ref.R_cam_from_world)) < 1e-12
        assert res.iterations == ref.iterations and res.initial_cost == pytest.approx(ref.initial_cost, rel=1e-12)
    else:  # λ_min's start taken: the translation weights (fixed at the start) differ slightly
        err = [float(np.degrees(so3.geodesic_angle(r.R_cam_from_world, R_gt)).mean()) for r in (res, ref)]
        assert abs(err[0] - err[1]) < 1e-3, err
    far = so3.exp(rng.normal(scale=np.deg2rad(3.0), size=(8, 3))) @ R_gt
    far[0] = R_gt[0]
    res, msg = _grrm_log(caplog, far, *args, options=cauchy)
    assert "skipped" not in msg
    ref, ref_msg = _grrm_log(caplog, far, *args, options=grrm.GRRMOptions(loss="cauchy", epipolar_trigger=None))
    assert msg == ref_msg
    assert np.max(so3.geodesic_angle(res.R_cam_from_world, ref.R_cam_from_world)) < 1e-12
    assert res.initial_cost == pytest.approx(ref.initial_cost, rel=1e-12)
    with pytest.raises(ValueError, match="epipolar_trigger"):
        grrm.GRRMOptions(epipolar_trigger=-1.0).validate()


def test_an_observation_matched_twice_through_one_edge(setup):
    """Two matches of one edge through the same keypoint (one-to-many matches): the per-view
    products add the two contributions' blocks (and their cross terms) as the pairs did."""
    from rotonly_cli.geometry import pairwise as pg

    p, prob, R, *_ = setup
    batch, obs_ids = prob.batch, prob.obs_ids
    twice = np.arange(int(batch.offsets[1]))[:5]  # five matches of edge 0, once more
    x_i = np.concatenate([batch.x_i[:batch.offsets[1]], batch.x_i[twice], batch.x_i[batch.offsets[1]:]])
    x_j = np.concatenate([batch.x_j[:batch.offsets[1]], batch.x_j[twice], batch.x_j[batch.offsets[1]:]])
    ids = np.concatenate([obs_ids[:batch.offsets[1]], obs_ids[twice], obs_ids[batch.offsets[1]:]])
    offsets = batch.offsets + np.r_[0, np.full(len(batch.offsets) - 1, len(twice))]
    doubled = pg.EdgeBatch(x_i, x_j, offsets)
    problem = grrm.GRRMSystem(8, prob.edge_views, doubled, ids)
    assert problem.layout.dense_pair_blocks
    V, J = grrm.grrm_residuals(R, prob.edge_views, doubled, ids, with_jacobian=True)
    sq = np.einsum("gk,gk->g", V, V)
    _, H, g, _ = problem.linearize(R, "cauchy", 1e9, False, True)  # a scale far beyond: weights ~1
    _, drho = robust.robust_rho(sq, "cauchy", 1e9)
    W = sp.diags(np.repeat(drho, 3))
    H_ref = (J.T @ W @ J).toarray()
    assert np.max(np.abs(H - H_ref)) <= 1e-12 * np.abs(H_ref).max()
