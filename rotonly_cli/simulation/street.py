"""A synthetic "street" scene for the geometry building-block tests and
scripts/bench/multiview_blocks.py: exact observations of points seen by several cameras.

A "street" of cameras along the x axis looking roughly at +z (random tilt), points in a slab
in front of them; a point is observed by every camera that sees it inside a 1000×1000 px
image at f = 1000 (normalized |x|, |y| < 0.5) with positive depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import so3


@dataclass
class StreetScene:
    R_cam_from_world: np.ndarray  # (n, 3, 3)
    centers: np.ndarray  # (n, 3)
    points: np.ndarray  # (N, 3)
    obs_point: np.ndarray  # (N_obs,) sorted
    obs_view: np.ndarray  # (N_obs,)
    obs_xy: np.ndarray  # (N_obs, 2) noise-free normalized coordinates


def make_street_scene(num_views: int, num_points: int, seed: int, spacing: float = 1.0,
                      max_tilt_deg: float = 8.0, depth: tuple[float, float] = (8.0, 12.0),
                      min_track_length: int = 2) -> StreetScene:
    rng = np.random.default_rng(seed)
    centers = np.stack([np.arange(num_views) * spacing,
                        rng.normal(scale=0.3, size=num_views),
                        rng.normal(scale=0.3, size=num_views)], axis=1)
    R = so3.random_rotations(num_views, rng, max_angle=np.radians(max_tilt_deg))
    x_range = (-3.0, (num_views - 1) * spacing + 3.0)
    points = np.stack([rng.uniform(*x_range, size=num_points),
                       rng.uniform(-3.0, 3.0, size=num_points),
                       rng.uniform(*depth, size=num_points)], axis=1)
    # candidate views per point: those within the x window (keeps memory O(N * window))
    half_window = int(np.ceil(0.6 * depth[1] / spacing)) + 2
    anchor = np.clip(np.round(points[:, 0] / spacing).astype(int), 0, num_views - 1)
    offsets = np.arange(-half_window, half_window + 1)
    cand_view = anchor[:, None] + offsets[None, :]
    cand_point = np.broadcast_to(np.arange(num_points)[:, None], cand_view.shape)
    inside = (cand_view >= 0) & (cand_view < num_views)
    cand_view, cand_point = cand_view[inside], cand_point[inside]
    p_cam = np.einsum("nij,nj->ni", R[cand_view], points[cand_point] - centers[cand_view])
    xy = p_cam[:, :2] / p_cam[:, 2:3]
    seen = (p_cam[:, 2] > 0.1) & (np.abs(xy) < 0.5).all(axis=1)
    counts = np.bincount(cand_point[seen], minlength=num_points)
    keep_point = counts >= min_track_length
    seen &= keep_point[cand_point]
    new_index = np.cumsum(keep_point) - 1
    obs_point = new_index[cand_point[seen]]
    order = np.lexsort((cand_view[seen], obs_point))
    return StreetScene(R, centers, points[keep_point], obs_point[order], cand_view[seen][order],
                 xy[seen][order])


def similarity_align_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Umeyama fit ``truth ≈ s A estimate + t``; returns (max residual, scale s)."""
    mu_e, mu_t = estimate.mean(0), truth.mean(0)
    E, T = estimate - mu_e, truth - mu_t
    U, S, Vt = np.linalg.svd(T.T @ E / len(E))
    D = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2] = -1.0
    A = (U * D) @ Vt
    s = float((S * D).sum() / (E**2).sum() * len(E))
    residual = truth - (s * E @ A.T + mu_t)
    return float(np.linalg.norm(residual, axis=1).max()), s
