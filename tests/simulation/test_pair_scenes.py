"""Two-view simulation scenes: defining geometry, visibility, seeds, noise, file round trip."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.geometry import so3
from rotonly_cli.simulation import pair_scenes as sim
from rotonly_cli.simulation.fivepoint import five_point_ransac, perturbed_rotation


def _homog(x: np.ndarray) -> np.ndarray:
    return np.column_stack([x, np.ones(len(x))])


@pytest.mark.parametrize("scene", sim.SCENES)
def test_noise_free_scene_is_consistent(scene: str) -> None:
    p = sim.simulate_twoview(scene, num_points=300, noise_px=0.0, rng=7)
    assert p.x_i.shape == p.x_j.shape == (300, 2)
    np.testing.assert_array_equal(p.x_i, p.x_i_true)
    assert np.all(so3.is_rotation(p.R_j_from_i))
    # R_j from OpenGV's bounded roll/pitch/yaw: each angle <= 0.5 rad -> total angle <= ~0.87 rad
    assert so3.geodesic_angle(np.eye(3), p.R_j_from_i) < np.sqrt(3) * 0.5 + 1e-9
    # t_ij = R_j (c_i - c_j) with c_i = 0
    np.testing.assert_allclose(p.t_j_from_i, -p.R_j_from_i @ p.center_j, atol=1e-15)
    # every point in front of both cameras and inside both 960x960 images
    P = p.points_in_i
    Q = P @ p.R_j_from_i.T + p.t_j_from_i
    assert np.all(P[:, 2] > 0) and np.all(Q[:, 2] > 0)
    half = 0.5 * 960 / p.focal
    for x in (p.x_i, p.x_j):
        assert np.abs(x).max() < half
    np.testing.assert_allclose(p.x_i, P[:, :2] / P[:, 2:], atol=1e-12)
    np.testing.assert_allclose(p.x_j, Q[:, :2] / Q[:, 2:], atol=1e-12)
    # eq:two-view_imaging_equation: the epipolar constraint x_j^T [t]x R x_i = 0 holds
    E = so3.hat(p.t_j_from_i) @ p.R_j_from_i
    assert np.abs(np.einsum("ki,ij,kj->k", _homog(p.x_j), E, _homog(p.x_i))).max() < 1e-12


def test_scene_defining_geometry() -> None:
    planar = sim.simulate_twoview("planar", num_points=200, noise_px=0.0, rng=1)
    np.testing.assert_allclose(planar.points_in_i[:, 2], 10.0, atol=1e-12)
    assert abs(planar.center_j[2] - 10.0) > 7.0  # the plane contains neither camera

    holo = sim.simulate_twoview("holoplane", num_points=200, noise_px=0.0, rng=2)
    normal = holo.extra["plane_normal"]
    assert abs(np.linalg.norm(normal) - 1.0) < 1e-12
    assert np.abs(holo.points_in_i @ normal).max() < 1e-12  # points on the plane through c_i = 0
    assert abs(holo.center_j @ normal) < 1e-12  # camera j's centre on it too
    assert abs(normal @ [0.0, 0.0, 1.0]) < 1e-12  # and (0, 0, 1)
    # rank P^S = 1 in a Holoplane: all theta_k are parallel (paper Corollary 1 case 2)
    theta = np.cross(_homog(holo.x_i) @ holo.R_j_from_i.T, _homog(holo.x_j))
    sv = np.linalg.svd(theta, compute_uv=False)
    assert sv[1] < 1e-10 * sv[0]

    line = sim.simulate_twoview("rankregular_line", num_points=200, noise_px=0.0, rng=3)
    d = line.extra["line_direction"]
    offsets = line.points_in_i - line.extra["line_point"]
    assert np.abs(np.cross(offsets, d)).max() < 1e-9  # all points on one line
    np.testing.assert_allclose(line.points_in_i[:, 2], 10.0, atol=1e-12)

    pure = sim.simulate_twoview("pure_rotation", num_points=200, noise_px=0.0, rng=4)
    assert np.linalg.norm(pure.t_j_from_i) == 0.0 and np.linalg.norm(pure.center_j) == 0.0
    rotated = _homog(pure.x_i) @ pure.R_j_from_i.T  # x_j ~ R_ij x_i: a homography, no parallax
    np.testing.assert_allclose(rotated[:, :2] / rotated[:, 2:], pure.x_j, atol=1e-12)

    standard = sim.simulate_twoview("standard", num_points=500, noise_px=0.0, rng=5)
    assert np.linalg.norm(standard.points_in_i, axis=1).max() <= 20.0
    assert 0.0 < np.linalg.norm(standard.center_j) <= 2.0
    # a generic scene: points span 3D (not coplanar)
    centred = standard.points_in_i - standard.points_in_i.mean(0)
    assert np.linalg.svd(centred, compute_uv=False)[2] > 1.0


def test_seed_reproduces_and_differs() -> None:
    a = sim.simulate_twoview("standard", num_points=100, noise_px=1.0, rng=11)
    b = sim.simulate_twoview("standard", num_points=100, noise_px=1.0, rng=11)
    c = sim.simulate_twoview("standard", num_points=100, noise_px=1.0, rng=12)
    np.testing.assert_array_equal(a.x_i, b.x_i)
    np.testing.assert_array_equal(a.R_j_from_i, b.R_j_from_i)
    assert not np.allclose(a.x_i, c.x_i[: len(a.x_i)])


@pytest.mark.parametrize("model", sim.NOISE_MODELS)
def test_noise_magnitude(model: str) -> None:
    p = sim.simulate_twoview("standard", num_points=4000, noise_px=2.0, rng=3, noise_model=model)
    delta_px = (p.x_i - p.x_i_true) * p.focal
    norms = np.linalg.norm(delta_px, axis=1)
    if model == "uniform":  # |delta| ~ U(0, 2): max <= 2, mean 1
        assert norms.max() <= 2.0 + 1e-9
        assert abs(norms.mean() - 1.0) < 0.05
    elif model == "gaussian":  # per-axis sigma 2
        assert abs(delta_px.std() - 2.0) < 0.1
    else:  # per-axis U(-2, 2): std 2/sqrt(3)
        assert np.abs(delta_px).max() <= 2.0 + 1e-9
        assert abs(delta_px.std() - 2.0 / np.sqrt(3.0)) < 0.05


def test_save_load_round_trip(tmp_path) -> None:
    p = sim.simulate_twoview("holoplane", num_points=50, noise_px=0.5, rng=9)
    path = sim.save_twoview(tmp_path / "edge.npz", p)
    q = sim.load_twoview(path)
    for name in ("R_j_from_i", "t_j_from_i", "x_i", "x_j", "x_i_true", "x_j_true", "points_in_i", "center_j"):
        np.testing.assert_array_equal(getattr(p, name), getattr(q, name))
    assert (q.scene, q.focal, q.image_size, q.noise_px, q.seed) == ("holoplane", 800.0, (960, 960), 0.5, 9)
    np.testing.assert_array_equal(q.extra["plane_normal"], p.extra["plane_normal"])
    assert [f.name for f in tmp_path.iterdir()] == ["edge.npz"]  # no temp file left behind


def test_load_rejects_bad_files(tmp_path) -> None:
    with pytest.raises(InputError, match="not found"):
        sim.load_twoview(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(InputError, match="format"):
        sim.load_twoview(bad)
    with pytest.raises(InputError, match="scene"):
        sim.simulate_twoview("cube")


def test_five_point_ransac_recovers_standard_pose() -> None:
    p = sim.simulate_twoview("standard", num_points=400, noise_px=0.0, rng=21)
    est = five_point_ransac(p.x_i, p.x_j, p.focal, threshold_px=0.5, seed=0)
    assert est.success and est.num_inliers >= 390
    assert so3.geodesic_angle(est.R_j_from_i, p.R_j_from_i) < 1e-6
    assert est.t_direction @ p.translation_direction > 1 - 1e-9
    rng = np.random.default_rng(0)
    R = perturbed_rotation(p.R_j_from_i, 2.0, rng)
    assert abs(np.rad2deg(so3.geodesic_angle(R, p.R_j_from_i)) - 2.0) < 1e-9
