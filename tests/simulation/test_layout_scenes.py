"""Multi-view simulation set-ups: layout, visibility, matches, initial rotations, corruption."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.geometry import so3
from rotonly_cli.simulation.layout_scenes import SETUPS, camera_layout, simulate_multiview


@pytest.mark.parametrize("setup", SETUPS)
def test_layout_spacing(setup: str) -> None:
    centers, headings = camera_layout(setup, 40, 10.0)
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    np.testing.assert_allclose(steps, 10.0, rtol=1e-12)
    np.testing.assert_allclose(centers.mean(axis=0), 0.0, atol=1e-9)  # array centred at the origin
    np.testing.assert_allclose(np.linalg.norm(headings, axis=1), 1.0, rtol=1e-12)


@pytest.mark.parametrize("setup", SETUPS)
def test_noise_free_problem_is_consistent(setup: str) -> None:
    p = simulate_multiview(setup, num_views=16, num_points=600, noise_px=0.0, rng=3, window=3,
                           min_shared=10, init="truth")
    scene = p.scene
    assert len(p.points_in_world) == 600 and np.all(p.visibility.sum(axis=0) >= 2)
    half = 0.5 * 960 / p.focal
    for v, pose in p.gt_poses.items():
        assert np.all(so3.is_rotation(pose.R_cam_from_world))
        X_cam = (p.points_in_world[p.visibility[v]] - pose.center) @ pose.R_cam_from_world.T
        assert np.all(X_cam[:, 2] > 0)  # chirality
        x = X_cam[:, :2] / X_cam[:, 2:]
        np.testing.assert_allclose(scene.normalized[v], x, atol=1e-12)
        assert np.abs(x).max() < half  # inside the 960x960 image
        np.testing.assert_allclose(scene.keypoints[v], x * p.focal + 480.0, atol=1e-9)
        if setup == "outward":  # optical axis horizontal and pointing away from the origin (+- tilt)
            axis = pose.R_cam_from_world[2]
            assert axis @ pose.center / np.linalg.norm(pose.center) > np.cos(np.deg2rad(8))
        else:  # looking up at the points above
            assert pose.R_cam_from_world[2, 2] > np.cos(np.deg2rad(8))
    assert len(scene.pairs) > 0
    for (i, j), pair in scene.pairs.items():
        assert i < j and len(pair.matches) >= 10
        # matched keypoints are the same 3D point: the epipolar constraint holds exactly
        R_ij = p.gt_relative_rotation(i, j)
        np.testing.assert_allclose(pair.R_j_from_i, R_ij, atol=1e-12)
        t_ij = p.gt_poses[j].R_cam_from_world @ (p.gt_poses[i].center - p.gt_poses[j].center)
        xi = np.column_stack([scene.normalized[i][pair.matches[:, 0]], np.ones(len(pair.matches))])
        xj = np.column_stack([scene.normalized[j][pair.matches[:, 1]], np.ones(len(pair.matches))])
        residual = np.einsum("ki,ij,kj->k", xj, so3.hat(t_ij / np.linalg.norm(t_ij)) @ R_ij, xi)
        assert np.abs(residual).max() < 1e-10
        gap = min(j - i, 16 - (j - i)) if setup != "linear" else j - i
        assert gap <= 3


def test_ransac_init_corruption_and_seed() -> None:
    kwargs = dict(num_views=12, num_points=1500, noise_px=1.0, window=2, min_shared=20, corrupt_fraction=0.25)
    p = simulate_multiview("circular", rng=5, **kwargs)
    q = simulate_multiview("circular", rng=5, **kwargs)
    keys = sorted(p.scene.pairs)
    assert keys == sorted(q.scene.pairs) and p.corrupted_pairs == q.corrupted_pairs
    for key in keys:
        np.testing.assert_array_equal(p.scene.pairs[key].R_j_from_i, q.scene.pairs[key].R_j_from_i)
    assert len(p.corrupted_pairs) == round(0.25 * len(keys))
    errors = {key: np.rad2deg(so3.geodesic_angle(p.scene.pairs[key].R_j_from_i, p.gt_relative_rotation(*key)))
              for key in keys}
    clean = [e for key, e in errors.items() if key not in p.corrupted_pairs]
    corrupt = [errors[key] for key in p.corrupted_pairs]
    assert np.median(clean) < 2.0  # 5-point RANSAC at 1 px: a fraction of a degree typically
    assert min(corrupt) > 5.0  # uniform random rotations are far from the truth
    gt = p.gt_scene()
    assert len(gt.poses) == 12 and gt.structure is not None and len(gt.structure.observations) == 1500
    v, kp = gt.structure.observations[0][0]
    assert p.visibility[v, 0] and 0 <= kp < len(p.scene.keypoints[v])


def test_bad_arguments() -> None:
    with pytest.raises(InputError, match="setup"):
        simulate_multiview("spiral")
    with pytest.raises(InputError, match="corrupt_fraction"):
        simulate_multiview("linear", corrupt_fraction=1.5)
