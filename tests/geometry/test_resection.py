"""Resection of camera centres with known rotations (geometry/resection.py)."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.resection import reprojection_errors, resect_centre, resect_left_out_views
from rotonly_cli.options import ResectionOptions


def _camera(rng, centre=(0.3, -0.2, 0.1)):
    R = so3.exp(rng.normal(scale=0.2, size=3))
    return R, np.asarray(centre, dtype=float)


def _seen(R, c, points):
    camera = (R @ (points - c).T).T
    return camera[:, :2] / camera[:, 2:3]


def _points_in_front(rng, R, c, num):
    # points 4-8 units ahead of the camera, spread over its field of view
    local = np.column_stack([rng.uniform(-0.5, 0.5, (num, 2)), np.ones(num)]) * rng.uniform(4, 8, (num, 1))
    return c + local @ R  # R^T local


def test_exact_keypoints_give_the_centre():
    rng = np.random.default_rng(1)
    R, c = _camera(rng)
    points = _points_in_front(rng, R, c, 50)
    centre, inliers = resect_centre(R, points, _seen(R, c, points), threshold=1e-6)
    np.testing.assert_allclose(centre, c, atol=1e-9)
    assert inliers.all()
    assert np.max(reprojection_errors(R, centre[None], points, _seen(R, c, points))) < 1e-12


def test_outliers_are_left_out_and_noise_averaged():
    """40 % of the keypoints anywhere in the image, the rest with 0.5 px of noise at f = 1000:
    the centre within a few thousandths of the points' depth, every outlier out."""
    rng = np.random.default_rng(2)
    R, c = _camera(rng)
    points = _points_in_front(rng, R, c, 200)
    xy = _seen(R, c, points) + rng.normal(scale=0.5e-3, size=(200, 2))
    wrong = rng.random(200) < 0.4
    xy[wrong] = rng.uniform(-0.5, 0.5, (int(wrong.sum()), 2))
    centre, inliers = resect_centre(R, points, xy, threshold=2e-3)
    assert np.linalg.norm(centre - c) < 0.02  # measured 0.004 (depths 4-8)
    assert not np.any(inliers & wrong) and inliers[~wrong].mean() > 0.95


def test_too_few_points_give_no_centre():
    R, _ = _camera(np.random.default_rng(3))
    centre, inliers = resect_centre(R, np.zeros((1, 3)), np.zeros((1, 2)), threshold=1e-3)
    assert np.isnan(centre).all() and inliers.shape == (1,) and not inliers.any()


def _tracks(rng, Rs, Cs, points, noise=0.0):
    """Every point seen by every view (sorted by point)."""
    obs_track = np.repeat(np.arange(len(points)), len(Rs))
    obs_view = np.tile(np.arange(len(Rs)), len(points))
    xy = np.concatenate([_seen(Rs[v], Cs[v], points[p:p + 1]) for p, v in zip(obs_track, obs_view)])
    return obs_track, obs_view, xy + rng.normal(scale=noise, size=xy.shape)


def test_left_out_views_are_resected_one_after_the_other():
    """Four views in a row; the last two without a centre, the third of them with too few
    points of its own (a view no track reaches): the two are resected, it stays out."""
    rng = np.random.default_rng(4)
    Rs = np.stack([so3.exp(rng.normal(scale=0.05, size=3)) for _ in range(5)])
    Cs = np.array([[k * 0.5, 0.0, 0.0] for k in range(5)])
    points = np.column_stack([rng.uniform(-3, 5, 300), rng.uniform(-2, 2, 300), rng.uniform(6, 10, 300)])
    obs_track, obs_view, xy = _tracks(rng, Rs, Cs, points, noise=0.3e-3)
    alone = (obs_view == 4) & (obs_track >= 10)  # view 4 sees only ten points
    obs_track, obs_view, xy = obs_track[~alone], obs_view[~alone], xy[~alone]
    start = Cs.copy()
    start[2:] = np.nan
    centres, added = resect_left_out_views(Rs, start, obs_track, obs_view, xy, np.full(5, 2e-3), np.arange(5))
    assert [entry["view"] for entry in added] in ([2, 3], [3, 2])
    np.testing.assert_allclose(centres[2:4], Cs[2:4], atol=0.01)
    assert np.isnan(centres[4]).all()
    np.testing.assert_array_equal(centres[:2], Cs[:2])  # the positioned ones untouched


@pytest.mark.parametrize("field, value", [("min_inliers", 400), ("min_inlier_fraction", 1.01)])
def test_a_centre_too_few_points_agree_with_is_not_kept(field, value):
    rng = np.random.default_rng(5)
    Rs = np.stack([np.eye(3)] * 3)
    Cs = np.array([[0.0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]])
    points = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(-2, 2, 300), rng.uniform(6, 10, 300)])
    obs_track, obs_view, xy = _tracks(rng, Rs, Cs, points)
    start = Cs.copy()
    start[2] = np.nan
    options = ResectionOptions(**{field: value})
    centres, added = resect_left_out_views(Rs, start, obs_track, obs_view, xy, np.full(3, 1e-3), [2], options)
    assert not added and np.isnan(centres[2]).all()
    centres, added = resect_left_out_views(Rs, start, obs_track, obs_view, xy, np.full(3, 1e-3), [2])
    assert len(added) == 1 and np.allclose(centres[2], Cs[2], atol=1e-9)
