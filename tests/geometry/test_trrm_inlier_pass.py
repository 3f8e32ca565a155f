"""TRRM's final inlier least-squares pass (geometry/trrm.py, TRRMOptions.final_inlier_pass)."""

import numpy as np
import pytest

from rotonly_cli.geometry import kernels, so3
from rotonly_cli.geometry import pairwise as pg
from rotonly_cli.geometry.trrm import TRRMOptions, _inlier_weights, optimize_rotations
from rotonly_cli.simulation.pair_scenes import simulate_twoview


@pytest.fixture(scope="module")
def standard_1px():
    """30 seeded Standard problems (1000 points, 1 px) and starts ~0.3° off."""
    problems = [simulate_twoview("standard", num_points=1000, noise_px=1.0, rng=500 + k) for k in range(30)]
    rng = np.random.default_rng(3)
    R_start = np.stack([so3.exp(rng.normal(scale=0.005, size=3)) @ p.R_j_from_i for p in problems])
    R_true = np.stack([p.R_j_from_i for p in problems])
    return problems, R_start, R_true


def _errors_deg(R: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    return np.rad2deg(so3.geodesic_angle(R, R_ref))


def test_inlier_pass_moves_robust_trrm_to_plain_least_squares(standard_1px):
    problems, R_start, R_true = standard_1px
    batch = pg.pack_edges([p.x_i for p in problems], [p.x_j for p in problems])
    R_plain = optimize_rotations(R_start, batch, TRRMOptions(loss="none"))[0]
    R_pass = optimize_rotations(R_start, batch, TRRMOptions())[0]
    R_cauchy = optimize_rotations(R_start, batch, TRRMOptions(final_inlier_pass=False))[0]
    err_plain, err_pass, err_cauchy = (_errors_deg(R, R_true).mean() for R in (R_plain, R_pass, R_cauchy))
    # measured: plain 0.01638°, with the pass 0.01641°, Cauchy only 0.02405°
    assert err_pass <= 1.03 * err_plain
    assert err_cauchy > 1.2 * err_plain  # what the pass repairs
    # distance to the least-squares optimum: measured 1.7e-3° with the pass, 1.5e-2° without
    assert _errors_deg(R_pass, R_plain).mean() < 0.3 * _errors_deg(R_cauchy, R_plain).mean()


def test_inlier_pass_keeps_robustness_to_gross_outliers(standard_1px):
    """5 % of x_j replaced by random points over the whole image. (At 10-20 % the robust
    TRRM from this start breaks down with or without the pass: see the task report.)"""
    problems, R_start, R_true = standard_1px
    x_i = [p.x_i for p in problems]
    R_clean = optimize_rotations(R_start, pg.pack_edges(x_i, [p.x_j for p in problems]), TRRMOptions())[0]
    rng = np.random.default_rng(4)
    x_j = []
    for p in problems:
        x = p.x_j.copy()
        bad = rng.choice(len(x), size=len(x) // 20, replace=False)
        x[bad] = rng.uniform(-0.6, 0.6, size=(bad.size, 2))
        x_j.append(x)
    batch = pg.pack_edges(x_i, x_j)
    R_pass = optimize_rotations(R_start, batch, TRRMOptions())[0]
    R_cauchy = optimize_rotations(R_start, batch, TRRMOptions(final_inlier_pass=False))[0]
    R_plain = optimize_rotations(R_start, batch, TRRMOptions(loss="none"))[0]
    clean_err = _errors_deg(R_clean, R_true).mean()
    # measured: 0.0189° vs 0.0164° clean; largest distance to the clean result 0.019°
    assert _errors_deg(R_pass, R_true).mean() < 1.3 * clean_err
    assert _errors_deg(R_pass, R_clean).max() < 0.05
    # Cauchy alone (0.153°, max 1.0° off) and plain least squares do far worse here
    assert _errors_deg(R_cauchy, R_true).mean() > 3 * clean_err
    assert _errors_deg(R_plain, R_true).mean() > 10 * clean_err


def test_inlier_weights_are_a_per_edge_k_sigma_cut():
    # two edges, residual norms chosen so that the median and the 3σ cut are known
    norms = np.array([1.0, 1.0, 1.0, 1.0, 4.4, 4.5, 10.0,  # edge 0: median 1 -> cut 3 x 1.4826 = 4.4478
                      2.0, 2.0, 2.0, 2.0, 8.8, 9.0, 2.0])  # edge 1: median 2 -> cut 8.8956
    rng = np.random.default_rng(0)
    points = [rng.normal(size=(7, 2)), rng.normal(size=(7, 2))]
    table = kernels.MatchTable.from_batch(pg.pack_edges(points, points))  # only its offsets matter
    w = _inlier_weights(norms ** 2, table, TRRMOptions())
    assert w.tolist() == [1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 1, 1, 0, 1]
    w4 = _inlier_weights(norms ** 2, table, TRRMOptions(inlier_threshold_sigmas=4.0))
    assert w4.tolist() == [1, 1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 1, 1]
    # noise-free: residuals ~1e-12 keep every match (threshold floored at min_loss_scale)
    assert _inlier_weights(np.full(14, 1e-24), table, TRRMOptions()).tolist() == [1.0] * 14


def test_inlier_pass_options_are_validated():
    with pytest.raises(ValueError, match="inlier_threshold_sigmas"):
        TRRMOptions(inlier_threshold_sigmas=0.0).validate()
    TRRMOptions(final_inlier_pass=False).validate()
