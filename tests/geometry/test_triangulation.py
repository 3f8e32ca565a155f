"""Batched multi-view triangulation (geometry/triangulation.py)."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.geometry.triangulation import TriangulationOptions, max_ray_angle_deg, triangulate_tracks

from helpers import make_street_scene


def triangulate(scene, xy, **option_overrides):
    return triangulate_tracks(scene.R_cam_from_world, scene.centers, scene.obs_point, scene.obs_view, xy,
                              options=TriangulationOptions(**option_overrides))


def test_noise_free_exact():
    scene = make_street_scene(15, 400, seed=1)
    result = triangulate(scene, scene.obs_xy)
    relative = np.linalg.norm(result.points_in_world - scene.points, axis=1) / np.linalg.norm(scene.points, axis=1)
    assert relative.max() < 1e-8
    assert result.valid.all()
    assert np.nanmax(result.mean_reprojection_error) < 1e-12


def test_linear_start_alone_is_exact_noise_free():
    scene = make_street_scene(8, 100, seed=2)
    result = triangulate(scene, scene.obs_xy, num_refinement_iterations=0)
    assert np.abs(result.points_in_world - scene.points).max() < 1e-8


@pytest.mark.parametrize("seed", [0, 1])
def test_one_pixel_noise(seed):
    # 1 px at f = 1000 = 1e-3 normalized, depth 8-12. Measured (seeds 0-5): median point
    # error 0.012-0.015 scene units, 95th percentile 0.05-0.12; mean reprojection ≈ 1.1e-3.
    scene = make_street_scene(15, 400, seed=seed)
    noisy = scene.obs_xy + np.random.default_rng(100 + seed).normal(scale=1e-3, size=scene.obs_xy.shape)
    result = triangulate(scene, noisy)
    error = np.linalg.norm(result.points_in_world - scene.points, axis=1)
    assert np.median(error) < 0.025
    assert np.percentile(error, 95) < 0.2
    assert result.valid.mean() > 0.98
    assert 0.8e-3 < np.median(result.mean_reprojection_error) < 1.4e-3
    # Gauss-Newton lowers the reprojection error of the linear start
    linear = triangulate(scene, noisy, num_refinement_iterations=0)
    assert np.mean(result.mean_reprojection_error) < np.mean(linear.mean_reprojection_error)


def test_points_behind_cameras_rejected():
    scene = make_street_scene(6, 60, seed=3)
    assert triangulate(scene, scene.obs_xy).in_front.all()
    # replace track 0 by a point 10 units behind its cameras: the lines through the
    # observations still meet there exactly, but the depth is negative
    first = scene.obs_point == 0
    point_behind = scene.centers[scene.obs_view[first]].mean(axis=0) - np.array([0.0, 0.0, 10.0])
    p_cam = np.einsum("nij,nj->ni", scene.R_cam_from_world[scene.obs_view[first]],
                      point_behind - scene.centers[scene.obs_view[first]])
    assert (p_cam[:, 2] < 0).all()
    xy = scene.obs_xy.copy()
    xy[first] = p_cam[:, :2] / p_cam[:, 2:]
    result = triangulate(scene, xy)
    assert not result.in_front[0] and not result.valid[0]
    assert np.abs(result.points_in_world[0] - point_behind).max() < 1e-8
    assert result.valid[1:].all()


def test_reprojection_and_parallax_rejection():
    scene = make_street_scene(8, 100, seed=4)
    xy = scene.obs_xy.copy()
    xy[np.flatnonzero(scene.obs_point == 7)[0]] += 0.05  # one gross outlier observation (50 px)
    result = triangulate(scene, xy)
    assert not result.valid[7] and result.mean_reprojection_error[7] > 4e-3
    assert np.delete(result.valid, 7).all()
    # a very far point: rays nearly parallel
    far = np.array([3.0, 0.0, 1e5])
    views = np.arange(8)
    assert (np.einsum("nij,nj->ni", scene.R_cam_from_world, far - scene.centers)[:, 2] > 0).all()
    p = np.einsum("nij,nj->ni", scene.R_cam_from_world, far - scene.centers)
    result_far = triangulate_tracks(scene.R_cam_from_world, scene.centers, np.zeros(8, dtype=np.int64),
                                    views, p[:, :2] / p[:, 2:])
    assert result_far.in_front[0] and result_far.max_parallax_deg[0] < 0.01 and not result_far.valid[0]


def test_max_ray_angle():
    rays = np.array([[0, 0, 1], [1, 0, 0], [0, 0, 1], [0, 1, 1]], dtype=float)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    angles = max_ray_angle_deg(rays, np.array([0, 2, 4]))
    assert np.allclose(angles, [90.0, 45.0])


def test_max_ray_angle_a_track_at_a_time_and_capped(monkeypatch):
    rays = np.array([[0, 0, 1], [0, 1, 1], [1, 0, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1]], dtype=float)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    offsets = np.array([0, 3, 3, 4, 6])  # tracks of 3, 0, 1 and 2 rays
    whole = max_ray_angle_deg(rays, offsets)
    monkeypatch.setattr("rotonly_cli.geometry.tracks.PAIRS_PER_CHUNK", 1)
    np.testing.assert_array_equal(max_ray_angle_deg(rays, offsets), whole)
    assert np.allclose(whole, [90.0, 0.0, 0.0, np.degrees(np.arccos(np.sqrt(2 / 3)))])
    # the first two rays only: 45 degrees apart
    assert np.allclose(max_ray_angle_deg(rays, offsets, max_views=2), [45.0, 0.0, 0.0, whole[3]])


def test_max_ray_angle_in_chunks_of_pairs_is_the_same(monkeypatch):
    rng = np.random.default_rng(4)
    length = rng.integers(1, 12, size=300)
    offsets = np.concatenate([[0], np.cumsum(length)])
    rays = rng.normal(size=(offsets[-1], 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    whole = max_ray_angle_deg(rays, offsets, max_views=8)
    monkeypatch.setattr("rotonly_cli.geometry.tracks.PAIRS_PER_CHUNK", 7)  # ~ one track a chunk, some of two
    np.testing.assert_array_equal(max_ray_angle_deg(rays, offsets, max_views=8), whole)
    # the python loop: max over all pairs of the first 8 rays
    expected = [max((np.degrees(np.arccos(np.clip(rays[s + a] @ rays[s + b], -1, 1)))
                     for a in range(min(n, 8)) for b in range(a + 1, min(n, 8))), default=0.0)
                for s, n in zip(offsets[:-1], length)]
    np.testing.assert_allclose(whole, expected, atol=1e-9)


def test_single_observation_track_is_invalid():
    scene = make_street_scene(4, 20, seed=5)
    result = triangulate_tracks(scene.R_cam_from_world, scene.centers, np.array([0, 1, 1]),
                                np.array([0, 0, 1]), np.array([[0.0, 0.0], [0.1, 0.0], [0.05, 0.0]]))
    assert not result.valid[0] and np.isnan(result.points_in_world[0]).all()


def test_closed_form_symmetric_solve_matches_lapack_and_flags_singular_systems():
    """The adjugate solve used per point agrees with numpy's LU solve on well- and
    ill-conditioned SPD systems (cond up to 1e8, like near-parallel rays) and returns NaN
    with ok=False for singular ones (a track whose rays are all parallel)."""
    from rotonly_cli.geometry.triangulation import _SYMMETRIC_ENTRIES, _solve_symmetric_3x3

    rng = np.random.default_rng(3)
    n = 400
    Q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    eigenvalues = np.stack([np.ones(n), 10.0 ** rng.uniform(-8, 0, n), 10.0 ** rng.uniform(-4, 0, n)], axis=1)
    A = np.einsum("nij,nj,nkj->nik", Q, eigenvalues, Q) * rng.uniform(0.1, 10, n)[:, None, None]
    A[-1] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])  # rank 1
    A[-2] = np.zeros((3, 3))
    b = rng.normal(size=(n, 3))
    packed = np.stack([A[:, i, j] for i, j in _SYMMETRIC_ENTRIES])
    x, ok = _solve_symmetric_3x3(packed, b.T)
    assert ok[:-2].all() and not ok[-2:].any() and np.isnan(x[:, -2:]).all()
    reference = np.linalg.solve(A[:-2], b[:-2, :, None])[..., 0]
    cond = np.linalg.cond(A[:-2])
    # forward error of either method is ~ cond·eps; both agree to that
    error = np.abs(x[:, :-2].T - reference).max(axis=1) / np.abs(reference).max(axis=1)
    assert np.all(error <= 1e-13 * cond)
    assert np.median(error) < 1e-9


def test_without_parallax_the_points_are_the_same_and_the_parallax_is_nan():
    scene = make_street_scene(8, 100, seed=3)
    noisy = scene.obs_xy + np.random.default_rng(7).normal(scale=1e-3, size=scene.obs_xy.shape)
    options = TriangulationOptions(min_parallax_deg=0.0)
    args = (scene.R_cam_from_world, scene.centers, scene.obs_point, scene.obs_view, noisy)
    full = triangulate_tracks(*args, options=options)
    bare = triangulate_tracks(*args, options=options, with_parallax=False)
    assert np.array_equal(full.points_in_world, bare.points_in_world)
    assert np.array_equal(full.valid, bare.valid)
    assert np.all(np.isnan(bare.max_parallax_deg)) and np.all(full.max_parallax_deg > 0)
    with pytest.raises(Exception, match="min_parallax_deg"):
        triangulate_tracks(*args, options=TriangulationOptions(min_parallax_deg=1.0), with_parallax=False)


@pytest.mark.parametrize("chunk", [1, 7, 100])
def test_in_slices_of_whole_points_the_numbers_are_the_same(monkeypatch, chunk):
    # a collection's observations are triangulated a slice of points at a time (memory): the
    # same numbers bit for bit, whatever the slice, with a point behind a camera and a point
    # too few rays among them
    from rotonly_cli.geometry import triangulation

    scene = make_street_scene(12, 300, seed=3)
    noisy = scene.obs_xy + np.random.default_rng(7).normal(scale=1e-3, size=scene.obs_xy.shape)
    noisy[:5] = -noisy[:5] * 40.0  # wreck the first point's rays
    whole = triangulate(scene, noisy)
    monkeypatch.setattr(triangulation, "CHUNK_OBSERVATIONS", chunk)
    sliced = triangulate(scene, noisy)
    for name in ("points_in_world", "valid", "mean_reprojection_error", "max_parallax_deg", "in_front"):
        np.testing.assert_array_equal(getattr(sliced, name), getattr(whole, name))
    assert not whole.valid.all() and whole.valid.mean() > 0.9
