"""Multi-view baselines: ROBA, Chatterjee (ℓ½ L1RA + IRLS) and pycolmap rotation averaging."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.baselines.references import chatterjee, pycolmap_rotation_averaging
from rotonly_cli.baselines.roba import ROBAOptions, ROBAProblem, roba
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry import so3
from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
from rotonly_cli.simulation.layout_scenes import simulate_multiview


def _scene(noise_px: float, seed: int = 0, num_views: int = 12):
    p = simulate_multiview("circular", num_views=num_views, num_points=1500, noise_px=noise_px, rng=seed,
                           init="truth", window=3)
    keys = sorted(p.scene.pairs)
    batch = pg.pack_edges([p.scene.normalized[i][p.scene.pairs[(i, j)].matches[:, 0]] for i, j in keys],
                          [p.scene.normalized[j][p.scene.pairs[(i, j)].matches[:, 1]] for i, j in keys])
    R_gt = np.stack([p.gt_poses[v].R_cam_from_world for v in range(num_views)])
    return np.array(keys), batch, R_gt


def _perturb(R: np.ndarray, deg: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = so3.exp(rng.normal(scale=np.radians(deg) / np.sqrt(3), size=(len(R), 3))) @ R
    out[0] = R[0]
    return out


def test_roba_cost_zero_at_truth_and_exact_recovery_noise_free() -> None:
    edges, batch, R_gt = _scene(0.0)
    problem = ROBAProblem(len(R_gt), edges, batch, ROBAOptions())
    cost_truth = problem.cost(so3.log(R_gt))
    assert cost_truth < 1e-5 * len(edges)  # sqrt of a rounding-level λ_min
    assert problem.cost(so3.log(_perturb(R_gt, 0.5, 1))) > 100 * cost_truth
    res = roba(R_gt, edges, batch)
    errors, _ = rotation_errors_after_alignment(res.R_cam_from_world, R_gt)
    assert np.radians(errors.max()) < 1e-8


def test_roba_gradient_matches_central_differences() -> None:
    edges, batch, R_gt = _scene(1.0)
    problem = ROBAProblem(len(R_gt), edges, batch, ROBAOptions(difference_step=1e-7))
    r = so3.log(_perturb(R_gt, 1.0, 2))
    _, grad = problem.cost_and_gradient(r)
    v, k = 3, 1
    d = np.zeros_like(r)
    d[v, k] = 1e-6
    numeric = (problem.cost(r + d) - problem.cost(r - d)) / 2e-6
    assert grad[v, k] == pytest.approx(numeric, rel=1e-3)


def test_roba_improves_perturbed_start() -> None:
    edges, batch, R_gt = _scene(1.0, seed=3)
    R0 = _perturb(R_gt, 1.0, 4)
    res = roba(R0, edges, batch)
    before = rotation_errors_after_alignment(R0, R_gt)[0].mean()
    after = rotation_errors_after_alignment(res.R_cam_from_world, R_gt)[0].mean()
    assert res.cost < 0.5 * res.initial_cost
    assert res.history[0] == pytest.approx(res.initial_cost) and min(res.history) == pytest.approx(res.cost)
    assert after < 0.3 * before


@pytest.mark.parametrize("method", [chatterjee, pycolmap_rotation_averaging])
def test_rotation_averaging_exact_and_denoises(method) -> None:
    rng = np.random.default_rng(7)
    n = 15
    R_gt = so3.random_rotations(n, rng)
    edges = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if j - i <= 4])
    R_rel = R_gt[edges[:, 1]] @ np.swapaxes(R_gt[edges[:, 0]], 1, 2)
    errors, _ = rotation_errors_after_alignment(method(n, edges, R_rel), R_gt)
    assert np.radians(errors.max()) < 1e-8
    noisy = so3.exp(rng.normal(scale=np.radians(1.0), size=(len(edges), 3))) @ R_rel
    noise_deg = np.degrees(so3.geodesic_angle(noisy, R_rel)).mean()
    errors, _ = rotation_errors_after_alignment(method(n, edges, noisy), R_gt)
    assert errors.mean() < 0.7 * noise_deg
