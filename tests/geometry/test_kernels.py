"""Lean TRRM evaluator, λ_min(Pˢ) from moments, padded medians, Procrustes on a MatchTable
(geometry/kernels/) against the readable reference implementations in geometry/pairwise.py,
and the contraction stopping rule of the lock-step LM (geometry/trrm.py)."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli import twoview
from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.trrm import TRRMOptions, optimize_rotations
from rotonly_cli.simulation.pair_scenes import simulate_twoview


def _mixed_batch(seed: int = 0, noise_px: float = 1.5):
    kinds = [("standard", 100), ("planar", 300), ("standard", 50), ("standard", 700), ("pure_rotation", 400),
             ("standard", 20), ("rankregular_line", 60)]
    problems = [simulate_twoview(s, num_points=n, noise_px=noise_px, rng=seed + k) for k, (s, n) in enumerate(kinds)]
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    rng = np.random.default_rng(seed)
    R = np.stack([so3.exp(rng.normal(scale=0.02, size=3)) @ p.R_j_from_i for p in problems])
    return problems, batch, R


@pytest.mark.parametrize("chunk", [64, 500, kernels.LEAN_CHUNK])
def test_lean_evaluator_equals_reference(chunk):
    _, batch, R = _mixed_batch()
    ref = pg.trrm_residuals(R, batch, with_jacobian=True)
    table = kernels.MatchTable.from_batch(batch, chunk=chunk)
    sq = np.empty(batch.x_i.shape[0])
    got = kernels.trrm_evaluate(R, table, jacobian=True, sq_out=sq, plain_ps=True)
    per_edge = lambda a: np.abs(a).reshape(len(a), -1).max(axis=1)  # noqa: E731
    assert np.max(np.abs(got["cost"] - ref.cost) / ref.cost) < 1e-12
    assert np.max(per_edge(got["JtJ"] - ref.JtJ) / per_edge(ref.JtJ)) < 1e-12
    assert np.max(per_edge(got["Jtr"] - ref.Jtr) / per_edge(ref.Jtr)) < 1e-11
    assert np.max(np.abs(got["t"] - ref.t)) < 1e-12
    assert np.max(np.abs(sq - np.einsum("mk,mk->m", ref.residuals, ref.residuals))) < 1e-15
    P = pg.ps_matrices(R, batch)
    assert np.max(per_edge(got["ps"] - P) / per_edge(P)) < 1e-13


def test_lean_evaluator_weights_unit_theta_and_partial_evaluation():
    _, batch, R = _mixed_batch(seed=3)
    rng = np.random.default_rng(1)
    w = rng.uniform(0.2, 1.0, batch.x_i.shape[0])
    old = kernels.trrm_normal_equations(R, batch.with_weights(w))
    table = kernels.MatchTable.from_batch(batch, w)
    full = kernels.trrm_evaluate(R, table, jacobian=True)
    assert np.max(np.abs(full["cost"] - old.cost) / old.cost) < 1e-11  # old: (√w r)², new: w r²
    # one edge 0.02 rad off has a match next to the epipole (JᵀJ ~ 3e6): ‖x_j × t‖ from the
    # dot identity keeps ~1e-11 of it there
    assert np.max(np.abs(full["JtJ"] - old.JtJ)) < 1e-10 * np.abs(old.JtJ).max()
    assert np.max(np.abs(full["Jtr"] - old.Jtr)) < 1e-10 * np.abs(old.Jtr).max()
    # an edge's numbers do not depend on which edges are evaluated with it, or how
    jac = np.array([1, 0, 1, 0, 0, 1, 0], bool)
    only = np.array([0, 1, 0, 0, 1, 0, 0], bool)
    part = kernels.trrm_evaluate(R, table, jacobian=jac, evaluate=only)
    assert np.array_equal(part["cost"][jac | only], full["cost"][jac | only])
    assert np.array_equal(part["JtJ"][jac], full["JtJ"][jac])
    assert np.all(part["cost"][~(jac | only)] == 0)
    # unit-length θ weights (robust start): the same residuals as trrm_match_terms with 1/‖θ‖²
    theta = pg.theta_vectors(R, batch)
    unit = batch.with_weights(1.0 / np.maximum(np.einsum("ma,ma->m", theta, theta), 1e-300))
    r = kernels.trrm_match_terms(R, unit, with_jacobian=False)["r"]
    sq = np.empty(len(theta))
    kernels.trrm_evaluate(R, kernels.MatchTable.from_batch(batch), unit_theta=True, sq_out=sq)
    assert np.max(np.abs(sq - np.einsum("mk,mk->m", r, r))) < 1e-12


def test_subset_keeps_match_positions():
    _, batch, R = _mixed_batch(seed=5)
    table = kernels.MatchTable.from_batch(batch)
    edges = np.array([5, 1, 3])
    sub = table.subset(edges)
    assert np.array_equal(sub.counts, table.counts[edges])
    assert np.array_equal(sub.data, table.data[:, sub.match_pos])
    got = kernels.trrm_evaluate(R[edges], sub, jacobian=True)
    ref = kernels.trrm_evaluate(R, table, jacobian=True)
    assert np.array_equal(got["JtJ"], ref["JtJ"][edges])


@pytest.mark.parametrize("weighted", [False, True])
def test_epipolar_phase_from_moments_equals_per_match_kernel(weighted):
    _, batch, R = _mixed_batch(seed=7)
    w = np.random.default_rng(2).uniform(0.2, 1.0, batch.x_i.shape[0]) if weighted else None
    # the pure-rotation edge has no parallax: its Pˢ is noise, where moments lose digits
    keep = np.array([0, 1, 2, 3, 5])
    b = batch.with_weights(w).subset(keep)
    old = kernels.epipolar_normal_equations(R[keep], b)
    got = kernels.epipolar_from_moments(R[keep], kernels.epipolar_moments(kernels.MatchTable.from_batch(b)))
    assert np.max(np.abs(got["cost"] - old.cost) / old.cost) < 1e-9
    assert np.max(np.abs(got["JtJ"] - old.JtJ).max(axis=(1, 2)) / np.abs(old.JtJ).max(axis=(1, 2))) < 1e-9
    assert np.max(np.abs(got["Jtr"] - old.Jtr).max(axis=1) / np.abs(old.Jtr).max(axis=1)) < 1e-9
    assert np.max(np.abs(np.abs(np.einsum("ea,ea->e", got["t"], old.t)) - 1.0)) < 1e-12


def test_smallest_eigenpair_lean_equals_twoview():
    rng = np.random.default_rng(4)
    n = 5000
    Q = so3.random_rotations(n, rng)
    w = np.sort(rng.uniform(0.0, 1.0, size=(n, 3)), axis=1)
    # near-double and exactly double smallest roots, and rank-deficient matrices
    w[:1000, 1] = w[:1000, 0] * (1.0 + rng.choice([1e-4, 1e-7, 1e-10, 0.0], size=1000))
    w[1000:1500, 0] = 0.0
    P = Q @ (w[:, :, None] * np.swapaxes(Q, 1, 2))
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    lam_ref, v_ref = pg.smallest_eigenpair(P)
    lam, v = kernels.smallest_eigenpair_lean(P[:, 0, 0], P[:, 0, 1], P[:, 0, 2], P[:, 1, 1], P[:, 1, 2], P[:, 2, 2])
    norm = np.linalg.norm(P, axis=(1, 2))
    assert np.max(np.abs(lam - lam_ref) / norm) < 1e-12
    resid = np.linalg.norm(np.einsum("eij,ej->ei", P, v) - lam[:, None] * v, axis=1)
    assert np.max(resid / norm) < 1e-9
    assert np.max(np.abs(np.linalg.norm(v, axis=1) - 1.0)) < 1e-12


def test_segment_median_equals_sorting_version():
    rng = np.random.default_rng(8)
    for trial in range(6):
        counts = rng.integers(6, 400, size=50) if trial else np.full(30, 100)
        offsets = np.concatenate([[0], np.cumsum(counts)])
        values = rng.random(offsets[-1]) ** 3
        if trial == 1:
            values[:] = 0.5  # ties everywhere
        batch = pg.EdgeBatch(np.zeros((offsets[-1], 3)), np.zeros((offsets[-1], 3)), offsets)
        assert np.array_equal(kernels.segment_median(values, offsets), pg.segment_median(values, batch))


def test_point_moments_and_procrustes_equal_twoview():
    _, batch, _ = _mixed_batch(seed=9)
    xi = batch.x_i / batch.x_i[:, 2:3]
    G_i, G_j = kernels.point_moments(pg.EdgeBatch(batch.x_i * 2.0, batch.x_j, batch.offsets))  # z = 2: divided
    assert np.max(np.abs(G_i - pg.outer_segment_sum(xi, xi, batch.offsets))) < 1e-12 * np.abs(G_i).max()
    assert np.array_equal(G_j, pg.outer_segment_sum(batch.x_j, batch.x_j, batch.offsets))
    table = kernels.MatchTable.from_batch(batch)
    for rounds in (0, 2):
        assert np.max(np.abs(kernels.best_pure_rotation(table, rounds) - pg.best_pure_rotation(batch, rounds))) < 1e-12


def test_contraction_stop_saves_iterations_not_accuracy():
    problems = [simulate_twoview("standard", num_points=400, noise_px=1.0, rng=40 + k) for k in range(20)]
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    rng = np.random.default_rng(6)
    R0 = np.stack([so3.exp(rng.normal(scale=0.01, size=3)) @ p.R_j_from_i for p in problems])
    R_a, _, c_a, it_a, conv_a = optimize_rotations(R0, batch, TRRMOptions())
    R_b, _, c_b, it_b, conv_b = optimize_rotations(R0, batch, TRRMOptions(contraction_stop_below=0.0))
    assert np.all(conv_a) and np.all(conv_b)
    assert it_a.sum() < it_b.sum()
    # the skipped steps are below the step tolerance (1e-7 rad); the noise-level error is ~3e-4
    assert np.max(so3.geodesic_angle(R_a, R_b)) < 1e-7
    # costs use the round-2 IRLS weights, set at slightly different round-1 rotations
    assert np.max(np.abs(c_a - c_b) / c_b) < 1e-4


def test_batched_refinement_equals_loop_on_ragged_edges():
    problems, _, R = _mixed_batch(seed=11, noise_px=1.0)
    batched = twoview.refine_rotations(R, [p.x_i for p in problems], [p.x_j for p in problems])
    for e, p in enumerate(problems):
        single = twoview.refine_rotation(R[e], p.x_i, p.x_j)
        assert single.kind == batched.kinds[e]
        assert np.array_equal(single.rotation, batched.rotations[e])
        assert single.iterations == batched.iterations[e]


def test_bulk_packing_equals_pack_edges():
    from rotonly_cli.twoview import _pack

    rng = np.random.default_rng(12)
    for cols in (2, 3):
        xs = [rng.random((n, cols)) for n in (6, 40, 13)]
        ys = [rng.random((n, cols)) for n in (6, 40, 13)]
        got, ref = _pack(xs, ys), pg.pack_edges(xs, ys)
        assert np.array_equal(got.x_i, ref.x_i) and np.array_equal(got.x_j, ref.x_j)
        assert np.array_equal(got.offsets, ref.offsets)
    mixed = _pack([rng.random((8, 2)), rng.random((8, 3))], [rng.random((8, 2)), rng.random((8, 3))])
    assert mixed.x_i.shape == (16, 3) and np.all(mixed.x_i[:8, 2] == 1.0)
    bad = [rng.random((8, 2)), rng.random((8, 2))]
    bad[1][3, 0] = np.nan
    with pytest.raises(ValueError, match=r"x_i\[1\]"):
        _pack(bad, [rng.random((8, 2)), rng.random((8, 2))])


def test_refined_translation_and_eigenvalues_equal_twoview_at_the_result():
    problems, batch, R = _mixed_batch(seed=13, noise_px=1.0)
    res = twoview.refine_rotations(R, [p.x_i for p in problems], [p.x_j for p in problems])
    regular = np.flatnonzero([k == twoview.SceneKind.REGULAR for k in res.kinds])
    assert regular.size >= 4
    t_ref, P, _ = pg.translation_directions(res.rotations[regular], batch.subset(regular))
    assert np.max(np.abs(res.translation_directions[regular] - t_ref)) < 1e-12
    # ρ is decided at the TRRM result; PURE_ROTATION edges then get the Procrustes rotation
    rho_ref = np.array([twoview.identify_scene(res.rotations[e], problems[e].x_i, problems[e].x_j).pure_rotation_ratio
                        for e in regular])
    assert np.max(np.abs(res.pure_rotation_ratios[regular] - rho_ref) / rho_ref) < 1e-12


@pytest.mark.parametrize("weighted", [False, True])
def test_reverse_mode_gradient_equals_forward_jacobian(weighted):
    _, batch, R = _mixed_batch(seed=15)
    w = np.random.default_rng(3).uniform(0.2, 1.0, batch.x_i.shape[0]) if weighted else None
    table = kernels.MatchTable.from_batch(batch, w)
    full = kernels.trrm_evaluate(R, table, jacobian=True)
    grad = kernels.trrm_evaluate(R, table, gradient=np.array([1, 1, 0, 1, 1, 1, 1], bool))
    rel = np.abs(grad["Jtr"] - full["Jtr"]).max(axis=1) / np.abs(full["Jtr"]).max(axis=1)
    assert np.max(np.delete(rel, 2)) < 1e-12
    assert np.all(grad["Jtr"][2] == 0) and np.all(grad["JtJ"] == 0)
    assert np.array_equal(grad["cost"], full["cost"])


def test_frozen_hessian_reaches_the_same_rotations():
    problems = [simulate_twoview("standard", num_points=400, noise_px=1.0, rng=60 + k) for k in range(20)]
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    rng = np.random.default_rng(9)
    R0 = np.stack([so3.exp(rng.normal(scale=0.015, size=3)) @ p.R_j_from_i for p in problems])
    R_a, _, _, it_a, conv_a = optimize_rotations(R0, batch, TRRMOptions(frozen_hessian_below=1e-3))
    R_b, _, _, it_b, conv_b = optimize_rotations(R0, batch, TRRMOptions())
    assert np.all(conv_a) and np.all(conv_b)
    assert np.max(so3.geodesic_angle(R_a, R_b)) < 1e-7
    assert it_a.sum() <= it_b.sum() + 2  # the contraction per step is unchanged
