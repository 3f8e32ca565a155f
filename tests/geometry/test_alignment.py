"""rotonly_cli.geometry.alignment: Umeyama, global rotation gauge, trace/3 angle."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.geometry import alignment, so3


def _random_similarity(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    return float(rng.uniform(0.1, 10.0)), so3.random_rotations(1, rng)[0], rng.normal(scale=5.0, size=3)


def test_umeyama_recovers_exact_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(12, 3))
    s, R, t = _random_similarity(rng)
    dst = s * src @ R.T + t
    s_hat, R_hat, t_hat = alignment.umeyama(src, dst)
    assert s_hat == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-10)
    np.testing.assert_allclose(alignment.apply_similarity(src, s_hat, R_hat, t_hat), dst, atol=1e-10)


def test_umeyama_without_scale_and_reflection_guard():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(8, 3))
    _, R, t = _random_similarity(rng)
    s_hat, R_hat, _ = alignment.umeyama(src, src @ R.T + t, with_scale=False)
    assert s_hat == 1.0
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    # a mirrored target must still give a proper rotation (det +1), like Eigen::umeyama
    mirrored = src * np.array([1.0, 1.0, -1.0])
    _, R_m, _ = alignment.umeyama(src, mirrored)
    assert np.linalg.det(R_m) == pytest.approx(1.0, abs=1e-12)


def test_umeyama_is_least_squares_optimum_under_noise():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3))
    s, R, t = _random_similarity(rng)
    dst = s * src @ R.T + t + rng.normal(scale=0.05, size=(20, 3))
    s_hat, R_hat, t_hat = alignment.umeyama(src, dst)
    cost = np.sum((dst - alignment.apply_similarity(src, s_hat, R_hat, t_hat)) ** 2)
    # any small perturbation of the parameters increases the cost
    for _k in range(20):
        dR = so3.exp(rng.normal(scale=1e-3, size=3))
        ds = 1.0 + rng.normal(scale=1e-3)
        dt = rng.normal(scale=1e-3, size=3)
        perturbed = alignment.apply_similarity(src, s_hat * ds, dR @ R_hat, t_hat + dt)
        assert np.sum((dst - perturbed) ** 2) > cost


def test_umeyama_rejects_bad_input():
    with pytest.raises(ValueError):
        alignment.umeyama(np.zeros((4, 3)), np.ones((4, 3)))
    with pytest.raises(ValueError):
        alignment.umeyama(np.zeros((4, 3)), np.ones((5, 3)))


def test_rotation_alignment_returns_per_camera_noise_exactly():
    """R_est_i = R_gt_i E_i A: after aligning, the errors are exactly the angles of the noise E_i.

    Every noise rotation comes with its inverse, so Σ E_i is symmetric positive definite and the
    chordal mean of R_gt_iᵀ R_est_i = E_i A projects exactly onto the gauge A.
    """
    rng = np.random.default_rng(4)
    n = 9
    R_gt = so3.random_rotations(n, rng)
    A = so3.random_rotations(1, rng)[0]
    noise_angles = np.radians(np.linspace(0.1, 2.0, n))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    E = so3.exp(np.concatenate([axes * noise_angles[:, None], -axes * noise_angles[:, None]]))
    R_gt2 = np.concatenate([R_gt, R_gt])
    R_est = R_gt2 @ E @ A
    errors, S = alignment.rotation_errors_after_alignment(R_est, R_gt2)
    np.testing.assert_allclose(S, A, atol=1e-12)
    np.testing.assert_allclose(errors, np.degrees(np.concatenate([noise_angles, noise_angles])), rtol=1e-9)


def test_rotation_alignment_is_gauge_invariant_and_zero_on_itself():
    rng = np.random.default_rng(5)
    R_gt = so3.random_rotations(7, rng)
    errors, S = alignment.rotation_errors_after_alignment(R_gt, R_gt)
    np.testing.assert_allclose(errors, 0.0, atol=1e-9)
    np.testing.assert_allclose(S, np.eye(3), atol=1e-12)
    R_est = R_gt @ so3.exp(rng.normal(scale=0.01, size=(7, 3)))
    B = so3.random_rotations(1, rng)[0]
    errors_a, _ = alignment.rotation_errors_after_alignment(R_est, R_gt)
    errors_b, S_b = alignment.rotation_errors_after_alignment(R_est @ B, R_gt)
    np.testing.assert_allclose(errors_b, errors_a, rtol=1e-9, atol=1e-12)
    assert np.all(errors_a > 0.0)
    # S is the chordal L2 optimum: the cost at S is below the cost at nearby rotations
    cost = np.sum((R_est @ B - R_gt @ S_b) ** 2)
    for _k in range(10):
        S_near = S_b @ so3.exp(rng.normal(scale=1e-3, size=3))
        assert np.sum((R_est @ B - R_gt @ S_near) ** 2) > cost


def test_relative_rotation_errors_need_no_alignment():
    rng = np.random.default_rng(6)
    R_gt = so3.random_rotations(4, rng)
    B = so3.random_rotations(1, rng)[0]
    noise = so3.exp(np.array([[0.0, 0.0, np.radians(1.0)], [0, 0, 0], [0, 0, 0], [0, 0, 0]]))
    R_est = noise @ R_gt @ B  # camera 0 rotated by 1 deg in its own frame
    errors = alignment.relative_rotation_errors(R_est, R_gt)
    assert alignment.pair_from_flat_index(4, np.arange(6)).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    np.testing.assert_allclose(errors, [1.0, 1.0, 1.0, 0.0, 0.0, 0.0], atol=1e-9)


def test_relative_rotation_errors_blocks_match_direct_formula():
    """Tiny blocks (many chunks) give the same numbers as R_ij = R_j R_iᵀ computed pair by pair."""
    rng = np.random.default_rng(7)
    n = 23
    R_gt = so3.random_rotations(n, rng)
    R_est = R_gt @ so3.exp(rng.normal(scale=0.05, size=(n, 3))) @ so3.random_rotations(1, rng)[0]
    i, j = np.triu_indices(n, k=1)
    direct = np.degrees(so3.geodesic_angle(R_gt[j] @ np.swapaxes(R_gt[i], -1, -2),
                                           R_est[j] @ np.swapaxes(R_est[i], -1, -2)))
    for max_block in (1, 7, 50, 10_000):
        np.testing.assert_allclose(alignment.relative_rotation_errors(R_est, R_gt, max_block=max_block),
                                   direct, rtol=1e-9)
    np.testing.assert_array_equal(alignment.pair_from_flat_index(n, np.arange(len(i))), np.stack([i, j], 1))


@pytest.mark.parametrize("theta_deg, expected", [(1.0, 0.81649), (5.0, 4.08205), (10.0, 8.1615),
                                                  (90.0, 70.529), (180.0, 109.471)])
def test_trace_over_3_angle_matches_openmvg_examples(theta_deg, expected):
    """formats.md §3.6 examples: acos((1 + 2 cos θ) / 3)."""
    R = so3.exp(np.array([0.3, -0.4, np.sqrt(0.75)]) * np.radians(theta_deg))
    assert alignment.trace_over_3_angle_deg(R) == pytest.approx(expected, abs=6e-4)
    assert alignment.trace_over_3_angle_deg(R) == pytest.approx(
        np.degrees(np.arccos((1 + 2 * np.cos(np.radians(theta_deg))) / 3)), rel=1e-12)


def test_trace_over_3_angle_is_clamped():
    """A non-orthonormal matrix with trace > 3 gives exactly 0, as OpenMVG's clamp does."""
    assert alignment.trace_over_3_angle_deg(np.eye(3) * 1.000001) == 0.0
    assert alignment.trace_over_3_angle_deg(-np.eye(3) * 1.5) == pytest.approx(180.0)
