"""The multi-view simulation's sparse visibility against the dense (views x points) computation
it replaced: the same (camera, point) observations, the same image positions to the bit, the
same keypoint indices, pairs, matches and ground-truth tracks, so a recipe (set-up, sizes,
seed) still gives the same files."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.simulation import layout_scenes
from rotonly_cli.simulation.layout_scenes import SETUPS, _point_sampler, camera_layout, simulate_multiview
from rotonly_cli.simulation.pair_scenes import bounded_rotation
from rotonly_cli.simulation.sparse_visibility import (
    CAMERAS_PER_GROUP,
    SparseVisibility,
    TrackLists,
    shared_keypoints,
    visible_observations,
)

HALF = np.array([0.6, 0.6])  # 960 px image, focal 800


def _cameras_and_points(setup: str, num_views: int, num_points: int, seed: int):
    rng = np.random.default_rng(seed)
    centers, headings = camera_layout(setup, num_views, 10.0)
    orient = layout_scenes._look_out if setup == "outward" else layout_scenes._look_up
    R = np.stack([bounded_rotation(rng, np.deg2rad(5.0)) @ orient(h) for h in headings])
    points = _point_sampler(setup, centers, rng, 400.0, (200.0, 3000.0), 200.0)(num_points)
    return R, centers, points


def _dense_in_image(points, R, centers, half=HALF):
    """The dense simulation's visibility test, all cameras x all points at once."""
    X_cam = np.einsum("vab,vnb->vna", R, points[None] - centers[:, None])
    depth = X_cam[..., 2]
    safe = np.where(depth > 1e-9, depth, 1.0)
    x = X_cam[..., :2] / safe[..., None]
    return (depth > 1e-9) & (np.abs(x[..., 0]) < half[0]) & (np.abs(x[..., 1]) < half[1])


@pytest.mark.parametrize("setup", SETUPS)
def test_culled_projection_finds_exactly_the_dense_observations(setup: str) -> None:
    num_views = 3 * CAMERAS_PER_GROUP + 5  # several groups of cameras, the last one short
    R, centers, points = _cameras_and_points(setup, num_views, 4000, seed=7)
    dense = _dense_in_image(points, R, centers)
    views, seen = visible_observations(points, R, centers, HALF)
    sparse = SparseVisibility.from_observations(views, seen, num_views, len(points))
    assert 5000 < dense.sum() < 0.5 * dense.size  # many observations, and culling has work to do
    np.testing.assert_array_equal(sparse.dense(), dense)
    np.testing.assert_array_equal(np.diff(sparse.offsets), dense.sum(axis=1))
    for v in (0, 40, num_views - 1):
        np.testing.assert_array_equal(sparse.points_of(v), np.flatnonzero(dense[v]))


def test_projection_of_a_subset_has_the_same_bits() -> None:
    """What makes the culled and per-view projections equal the dense ones bit for bit."""
    R, centers, points = _cameras_and_points("circular", 40, 5000, seed=3)
    full = np.einsum("vab,vnb->vna", R, points[None] - centers[:, None])
    rng = np.random.default_rng(0)
    for num_cameras, num_points in [(1, 1), (1, 17), (3, 1000), (32, 333), (40, 5000)]:
        cameras = np.sort(rng.choice(40, num_cameras, replace=False))
        chosen = np.sort(rng.choice(5000, num_points, replace=False))
        part = np.einsum("vab,vnb->vna", R[cameras], points[chosen][None] - centers[cameras][:, None])
        assert np.array_equal(part, full[np.ix_(cameras, chosen)])


def _window_pairs_dense(num_views: int, window: int, cyclic: bool) -> np.ndarray:
    i, j = np.triu_indices(num_views, k=1)
    gap = j - i
    if cyclic:
        gap = np.minimum(gap, num_views - gap)
    keep = gap <= window
    return np.column_stack([i[keep], j[keep]])


@pytest.mark.parametrize("cyclic", [False, True])
def test_window_pairs_equal_the_all_pairs_filter(cyclic: bool) -> None:
    for num_views in (3, 4, 5, 8, 21, 60):
        for window in (1, 2, 3, 4, 10, 30, 100):
            expected = _window_pairs_dense(num_views, window, cyclic)
            got = layout_scenes._window_pairs(num_views, window, cyclic)
            assert got.dtype == expected.dtype and np.array_equal(got, expected), (num_views, window)
    assert len(layout_scenes._window_pairs(10_000, 3, cyclic)) == 30_000 - (0 if cyclic else 6)


@pytest.mark.parametrize("setup", ["linear", "outward"])
def test_problem_equals_the_dense_reference(setup: str) -> None:
    """Keypoints, matches and GT tracks of a simulated problem, against the dense formulas."""
    p = simulate_multiview(setup, num_views=40, num_points=2000, noise_px=0.0, rng=2, window=3, min_shared=10,
                           init="truth", swapped_fraction=0.0)
    dense = p.visibility
    assert dense.shape == (40, 2000) and np.all(dense.sum(axis=0) >= 2)
    R = np.stack([p.gt_poses[v].R_cam_from_world for v in range(40)])
    centers = np.stack([p.gt_poses[v].center for v in range(40)])
    X_cam = np.einsum("vab,vnb->vna", R, p.points_in_world[None] - centers[:, None])
    x_true = X_cam[..., :2] / X_cam[..., 2:3]
    kp_index = np.cumsum(dense, axis=1) - 1
    for v in range(40):  # noise-free: the normalized keypoints are the true projections, to the bit
        assert np.array_equal(p.scene.normalized[v], x_true[v, dense[v]])
    cyclic = setup != "linear"
    assert sorted(p.scene.pairs) == [tuple(map(int, key)) for key in _window_pairs_dense(40, 3, cyclic)
                                     if np.sum(dense[key[0]] & dense[key[1]]) >= 10]
    for (i, j), pair in p.scene.pairs.items():
        shared = np.flatnonzero(dense[i] & dense[j])
        np.testing.assert_array_equal(pair.matches, np.column_stack([kp_index[i, shared], kp_index[j, shared]]))
        np.testing.assert_array_equal(np.column_stack(shared_keypoints(p.sparse_visibility, i, j)), pair.matches)
    observations = p.gt_scene().structure.observations
    expected = [[(int(v), int(kp_index[v, k])) for v in np.flatnonzero(dense[:, k])] for k in range(2000)]
    assert len(observations) == 2000 and list(observations) == expected
    assert observations[-1] == expected[-1] and observations[3:5] == expected[3:5]


def test_track_lists_index_like_a_list() -> None:
    tracks = TrackLists(np.array([2, 0, 1]), np.array([[0, 5], [2, 1], [1, 7]]))
    assert list(tracks) == [[(0, 5), (2, 1)], [], [(1, 7)]] and len(tracks) == 3
    assert tracks[-1] == [(1, 7)]
    with pytest.raises(IndexError):
        tracks[3]
