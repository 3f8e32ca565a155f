"""Two-view baselines (PA, Kneip eigensolver, OpenGV-style non-linear): exact recovery without
noise, improvement from a perturbed start with noise, and the building blocks they rest on."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.baselines.kneip import (
    cayley_to_rotation,
    kneip_matrices,
    kneip_sums,
    refine_kneip_eigen,
    smallest_eigenvalue_and_gradient,
    unit_rows,
)
from rotonly_cli.baselines.opengv_nonlinear import (
    optimize_nonlinear_twoview,
    rotation_to_cayley,
    triangulate_midpoint_frame1,
)
from rotonly_cli.baselines.pa import pa_residuals, pose_adjust_twoview
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3
from rotonly_cli.simulation.fivepoint import perturbed_rotation
from rotonly_cli.simulation.pair_scenes import simulate_twoview


def _problems(noise_px: float, seeds: range, num_points: int = 200):
    return [simulate_twoview("standard", num_points=num_points, noise_px=noise_px, rng=s) for s in seeds]


def _starts(problems, angle_deg: float, seed: int):
    rng = np.random.default_rng(seed)
    R0 = np.stack([perturbed_rotation(p.R_j_from_i, angle_deg, rng) for p in problems])
    t0 = [p.translation_direction + 0.03 * rng.normal(size=3) for p in problems]
    return R0, t0


def test_kneip_matrix_from_sums_equals_direct_sum_and_ps() -> None:
    problems = _problems(1.0, range(3))
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    R = np.stack([p.R_j_from_i for p in problems])
    M = kneip_matrices(R, kneip_sums(batch))
    f1, f2 = unit_rows(batch.x_j), unit_rows(batch.x_i)
    n = np.cross(f1, np.einsum("mab,mb->ma", np.repeat(R, batch.counts, axis=0), f2))
    np.testing.assert_allclose(M, pg.outer_segment_sum(n, n, batch.offsets), atol=1e-12)
    # Kneip's M = Pˢ of bearing-normalised observations (algorithms.md §4): same λ_min as the
    # paper's epipolar cost, which pg.epipolar_residuals evaluates per match
    lam = pg.symmetric_eigenvalues3(M)[:, 0]
    np.testing.assert_allclose(lam, pg.epipolar_residuals(R, batch).cost, rtol=1e-8, atol=1e-15)


def test_kneip_gradient_matches_finite_differences() -> None:
    problems = _problems(2.0, range(2))
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    R0, _ = _starts(problems, 2.0, 0)
    G = kneip_sums(batch)
    _, _, grad = smallest_eigenvalue_and_gradient(R0, G)
    h = 1e-6
    numeric = np.stack([(smallest_eigenvalue_and_gradient(so3.exp(h * e) @ R0, G)[0]
                         - smallest_eigenvalue_and_gradient(so3.exp(-h * e) @ R0, G)[0]) / (2 * h)
                        for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-9 * np.abs(grad).max())


def test_cayley_round_trip() -> None:
    rng = np.random.default_rng(3)
    R = so3.random_rotations(5, rng, max_angle=2.5)
    for Rk in R:
        np.testing.assert_allclose(cayley_to_rotation(rotation_to_cayley(Rk)), Rk, atol=1e-12)


def test_kneip_eigen_exact_recovery_noise_free() -> None:
    problems = _problems(0.0, range(4))
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    R0, _ = _starts(problems, 1.0, 1)
    res = refine_kneip_eigen(R0, batch)
    truth = np.stack([p.R_j_from_i for p in problems])
    assert np.all(so3.geodesic_angle(res.rotations, truth) < 1e-8)
    t_true = np.stack([p.translation_direction for p in problems])
    assert np.all(np.einsum("ea,ea->e", res.translation_directions, t_true) > 1 - 1e-12)  # sign by chirality
    assert np.all(res.smallest_eigenvalues < 1e-12) and np.all(res.initial_eigenvalues > 1e-4)


def test_kneip_eigen_improves_perturbed_start() -> None:
    problems = _problems(1.0, range(100, 106))
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    R0, _ = _starts(problems, 1.0, 2)
    res = refine_kneip_eigen(R0, batch)
    truth = np.stack([p.R_j_from_i for p in problems])
    before = np.degrees(so3.geodesic_angle(R0, truth))
    after = np.degrees(so3.geodesic_angle(res.rotations, truth))
    assert np.all(res.smallest_eigenvalues < res.initial_eigenvalues)
    assert after.max() < 0.3 and after.mean() < 0.25 * before.mean()


def test_pa_residual_vanishes_at_truth_noise_free() -> None:
    p = _problems(0.0, range(1))[0]
    r = pa_residuals(p.R_j_from_i, p.translation_direction, p.x_i, p.x_j)
    assert np.abs(r).max() < 1e-12
    # ... and is invariant to the scale (not the sign) of t (eq:PA1)
    np.testing.assert_allclose(pa_residuals(p.R_j_from_i, 3.7 * p.t_j_from_i, p.x_i, p.x_j), r, atol=1e-12)
    r_perturbed = pa_residuals(perturbed_rotation(p.R_j_from_i, 0.1, np.random.default_rng(0)),
                               p.translation_direction, p.x_i, p.x_j)
    assert np.abs(r_perturbed).max() > 1e-5


@pytest.mark.parametrize("method", ["pa", "nonlinear"])
def test_pose_refiners_exact_recovery_noise_free(method: str) -> None:
    problems = _problems(0.0, range(10, 12), num_points=150)
    R0, t0 = _starts(problems, 1.0, 4)
    for p, R, t in zip(problems, R0, t0):
        fn = pose_adjust_twoview if method == "pa" else optimize_nonlinear_twoview
        res = fn(R, t, p.x_i, p.x_j)
        assert so3.geodesic_angle(res.R_j_from_i, p.R_j_from_i) < 1e-8
        assert res.t_direction @ p.translation_direction > 1 - 1e-12
        assert res.cost < 1e-20 < res.initial_cost


@pytest.mark.parametrize("method", ["pa", "nonlinear"])
def test_pose_refiners_improve_perturbed_start(method: str) -> None:
    problems = _problems(1.0, range(200, 204))
    R0, t0 = _starts(problems, 1.0, 5)
    before, after = [], []
    for p, R, t in zip(problems, R0, t0):
        fn = pose_adjust_twoview if method == "pa" else optimize_nonlinear_twoview
        res = fn(R, t, p.x_i, p.x_j)
        assert res.cost < res.initial_cost
        before.append(np.degrees(so3.geodesic_angle(R, p.R_j_from_i)))
        after.append(np.degrees(so3.geodesic_angle(res.R_j_from_i, p.R_j_from_i)))
    assert max(after) < 0.3 and np.mean(after) < 0.25 * np.mean(before)


def test_midpoint_triangulation_noise_free() -> None:
    p = _problems(0.0, range(1))[0]
    R12 = p.R_j_from_i.T
    t12 = p.center_j  # centre of camera j in frame i (= world)
    P = triangulate_midpoint_frame1(R12, t12, unit_rows(p.x_i), unit_rows(p.x_j))
    np.testing.assert_allclose(P, p.points_in_i, rtol=1e-9, atol=1e-9)
