"""Two-view BA baseline: exact recovery without noise, improvement from a perturbed start."""

from __future__ import annotations

import numpy as np

from rotonly_cli.baselines.twoview_ba import bundle_adjust_twoview, triangulate_midpoint
from rotonly_cli.geometry import so3
from rotonly_cli.simulation.fivepoint import perturbed_rotation
from rotonly_cli.simulation.pair_scenes import simulate_twoview


def test_triangulation_noise_free_is_exact() -> None:
    p = simulate_twoview("standard", num_points=100, noise_px=0.0, rng=1)
    t = p.t_j_from_i
    P = triangulate_midpoint(p.R_j_from_i, t, p.x_i, p.x_j)
    np.testing.assert_allclose(P, p.points_in_i, rtol=1e-9, atol=1e-9)


def test_exact_recovery_noise_free() -> None:
    p = simulate_twoview("standard", num_points=150, noise_px=0.0, rng=2)
    rng = np.random.default_rng(0)
    R0 = perturbed_rotation(p.R_j_from_i, 1.0, rng)
    t0 = p.translation_direction + 0.03 * rng.normal(size=3)
    result = bundle_adjust_twoview(R0, t0, p.x_i, p.x_j)
    assert result.success
    assert so3.geodesic_angle(result.R_j_from_i, p.R_j_from_i) < 1e-8
    assert np.arccos(np.clip(result.t_direction @ p.translation_direction, -1, 1)) < 1e-7
    assert result.cost < 1e-20 < result.initial_cost


def test_improves_perturbed_start_with_noise() -> None:
    errors_before, errors_after = [], []
    for seed in range(3):
        p = simulate_twoview("standard", num_points=200, noise_px=1.0, rng=100 + seed)
        rng = np.random.default_rng(seed)
        R0 = perturbed_rotation(p.R_j_from_i, 1.0, rng)
        result = bundle_adjust_twoview(R0, p.translation_direction, p.x_i, p.x_j)
        errors_before.append(np.rad2deg(so3.geodesic_angle(R0, p.R_j_from_i)))
        errors_after.append(np.rad2deg(so3.geodesic_angle(result.R_j_from_i, p.R_j_from_i)))
        assert result.cost < result.initial_cost
    # 1 deg start -> BA lands at the noise level (~0.1 deg at 1 px with 200 points)
    assert max(errors_after) < 0.3
    assert np.mean(errors_after) < 0.25 * np.mean(errors_before)
