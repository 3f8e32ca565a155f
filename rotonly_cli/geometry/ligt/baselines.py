"""Global centres against the edges' own translation directions: the angle between each
edge's t_ij axis and the baseline the poses give it, and the views whose edges disagree
(LiGT's baseline check, algorithms.md §1; stages/translate)."""

from __future__ import annotations

import numpy as np


def baseline_disagreement_deg(R_cam_from_world: np.ndarray, centers: np.ndarray, edge_views: np.ndarray,
                              t_dirs: np.ndarray) -> np.ndarray:
    """Per edge (i, j) (``edge_views`` (E, 2) view indices, ``t_dirs`` (E, 3) the edge's own
    unit translation t_ij, x_j ~ R_ij x_i + t_ij): the angle in degrees between the axis of
    t_ij and the baseline the global poses give it, R_j (c_i - c_j), signs ignored (a sign is
    the two-view chirality's, the axis is what a centre must agree with). NaN where either
    vector is zero or not finite."""
    R = np.asarray(R_cam_from_world, dtype=float)
    C = np.asarray(centers, dtype=float)
    i, j = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2).T
    baseline = np.einsum("eab,eb->ea", R[j], C[i] - C[j])
    t = np.asarray(t_dirs, dtype=float).reshape(-1, 3)
    norms = np.linalg.norm(baseline, axis=1) * np.linalg.norm(t, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.abs(np.einsum("ea,ea->e", baseline, t)) / norms
    angle = np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))
    return np.where(np.isfinite(norms) & (norms > 0), angle, np.nan)


def views_off_their_baselines(angles_deg: np.ndarray, edge_views: np.ndarray, num_views: int,
                              max_disagreement_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(median angle over each view's edges (NaN for a view without one), indices of the
    views whose median exceeds ``max_disagreement_deg``), from :func:`baseline_disagreement_deg`."""
    angles = np.asarray(angles_deg, dtype=float)
    ends = np.asarray(edge_views, dtype=np.int64).reshape(-1, 2)
    finite = np.isfinite(angles)
    median = np.full(num_views, np.nan)
    view_of = np.concatenate([ends[finite, 0], ends[finite, 1]])
    angle_of = np.concatenate([angles[finite], angles[finite]])
    # every view's angles sorted within its run of the sorted views: the median is the mean of
    # the run's two middle entries (one entry for an odd count), as np.median takes it
    order = np.lexsort((angle_of, view_of))
    sorted_angles = angle_of[order]
    counts = np.bincount(view_of, minlength=num_views)
    has = np.flatnonzero(counts)
    starts = (np.cumsum(counts) - counts)[has]
    low, high = sorted_angles[starts + (counts[has] - 1) // 2], sorted_angles[starts + counts[has] // 2]
    median[has] = (low + high) / 2.0
    return median, np.flatnonzero(np.nan_to_num(median, nan=0.0) > max_disagreement_deg)
