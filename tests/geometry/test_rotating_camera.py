"""The focal length of a rotating camera (geometry/rotating_camera.py): exact on noise-free
pure rotations from far-off guesses; a plane seen from two places fits no rotation."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.rotating_camera import pure_rotation_residuals_px, rotating_camera_focal

FOCAL = 1380.0


def _pairs(rng: np.random.Generator, centres: np.ndarray, points: np.ndarray, noise_px: float = 0.0):
    """Pixel offsets from the principal point of ``points`` in cameras at ``centres`` turned
    15° apart about the vertical (plus a small tilt), matched between neighbours."""
    rotations = [so3.exp(np.array([0.02 * k, np.deg2rad(15.0) * k, 0.0])) for k in range(len(centres))]
    pixels, visible = [], []
    for R, c in zip(rotations, centres):
        X = (points - c) @ R.T
        u = FOCAL * X[:, :2] / X[:, 2:]
        pixels.append(u + rng.normal(scale=noise_px, size=u.shape))
        visible.append((X[:, 2] > 0) & (np.abs(u[:, 0]) < 768) & (np.abs(u[:, 1]) < 512))
    u_i, u_j = [], []
    for k in range(len(centres) - 1):
        shared = visible[k] & visible[k + 1]
        u_i.append(pixels[k][shared])
        u_j.append(pixels[k + 1][shared])
    return u_i, u_j


def _panorama_points(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    directions = rng.normal(size=(n, 3)) * [1.0, 0.3, 1.0]
    return directions / np.linalg.norm(directions, axis=1, keepdims=True) * rng.uniform(5, 40, (n, 1))


@pytest.mark.parametrize("guess", [0.5, 0.83, 1.2, 2.0])
def test_the_focal_of_a_noise_free_rotating_camera_is_recovered(guess):
    rng = np.random.default_rng(0)
    u_i, u_j = _pairs(rng, np.zeros((5, 3)), _panorama_points(rng))
    fit = rotating_camera_focal(u_i, u_j, guess * FOCAL)
    assert fit.interior
    assert fit.focal_px == pytest.approx(FOCAL, rel=1e-6)
    assert np.all(fit.residual_px < 1e-6)


def test_noisy_pure_rotations_give_the_focal_to_a_tenth_of_a_percent():
    rng = np.random.default_rng(1)
    u_i, u_j = _pairs(rng, np.zeros((5, 3)), _panorama_points(rng), noise_px=0.5)
    fit = rotating_camera_focal(u_i, u_j, 1.2 * FOCAL)
    assert fit.focal_px == pytest.approx(FOCAL, rel=1e-3)
    assert np.median(fit.residual_px) < 1.0  # the noise level: 0.5 px per coordinate


def test_a_plane_seen_from_two_places_fits_no_rotation():
    """A homography explains it, but not one of the form K R K⁻¹: the residual stays far above
    the noise at every focal length (RotatingCameraFit.residual_px; the stage's limit is 2 px)."""
    rng = np.random.default_rng(2)
    wall = np.column_stack([rng.uniform(-20, 20, 3000), rng.uniform(-5, 5, 3000), np.full(3000, 10.0)])
    wall = so3.exp(np.array([0.0, np.deg2rad(30), 0.0])) @ wall.T
    centres = np.array([[-1.5 + 0.75 * k, 0.0, 0.0] for k in range(5)])
    u_i, u_j = _pairs(rng, centres, wall.T)
    fit = rotating_camera_focal(u_i, u_j, FOCAL)
    assert np.median(fit.residual_px) > 5.0
    assert np.all(pure_rotation_residuals_px(u_i, u_j, FOCAL) > 2.0)  # at the true focal: 4.7-13.5 px
