"""Aligning an estimate to ground truth: similarity on camera centres, global rotation gauge.

Pure numpy. Conventions (architecture.md): ``R_i`` is ``R_cam_from_world``. Two
reconstructions of the same cameras differ by a world-frame similarity ``X_gt = s A X_est + t``,
so ``c_gt_i = s A c_est_i + t`` and ``R_est_i = R_gt_i A`` (the gauge of world->camera rotations
is a *right* multiplication).
"""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry import so3


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991, as Eigen::umeyama).

    ``src``, ``dst``: (n, 3). Returns ``(s, R, t)``; ``s = 1`` when ``with_scale`` is False.
    This is the start point of OpenMVG's ``FindRTS`` (formats.md §3.5); the cost is the one its
    ``Refine_RTS`` minimises, so no further refinement is needed.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two (n, 3) arrays, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 2:
        raise ValueError("umeyama needs at least 2 points")
    mean_src = src.mean(axis=0)
    mean_dst = dst.mean(axis=0)
    src_centred = src - mean_src
    dst_centred = dst - mean_dst
    covariance = dst_centred.T @ src_centred / n
    U, singular_values, Vt = np.linalg.svd(covariance)
    reflection_fix = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        reflection_fix[2] = -1.0
    R = (U * reflection_fix) @ Vt
    if with_scale:
        src_variance = np.sum(src_centred ** 2) / n
        if src_variance <= 0.0:
            raise ValueError("umeyama: all source points coincide, scale is undefined")
        s = float(singular_values @ reflection_fix / src_variance)
    else:
        s = 1.0
    t = mean_dst - s * R @ mean_src
    return s, R, t


def apply_similarity(points: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``s R p + t`` for each row p of ``points`` (n, 3)."""
    return s * np.asarray(points, dtype=float) @ R.T + t


def align_rotations_l2(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Best global gauge rotation ``S`` with ``R_est_i ≈ R_gt_i S`` (i.e. ``R_gt_i ≈ R_est_i Sᵀ``).

    Minimises the chordal cost ``Σ ‖R_est_i − R_gt_i S‖_F²``; the solution is the chordal L2
    mean of ``R_gt_iᵀ R_est_i`` projected onto SO(3). ``R_est``, ``R_gt``: (n, 3, 3) world->camera.
    """
    R_est = np.asarray(R_est, dtype=float).reshape(-1, 3, 3)
    R_gt = np.asarray(R_gt, dtype=float).reshape(-1, 3, 3)
    if R_est.shape != R_gt.shape or R_est.shape[0] == 0:
        raise ValueError(f"align_rotations_l2 needs two equal non-empty (n, 3, 3) stacks, got {R_est.shape}, "
                         f"{R_gt.shape}")
    mean_gt_to_est = np.einsum("nji,njk->ik", R_gt, R_est)  # Σ R_gt_iᵀ R_est_i
    return so3.project_to_so3(mean_gt_to_est)


def rotation_errors_after_alignment(R_est: np.ndarray, R_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-camera geodesic error (deg) of ``R_gt_iᵀ R_est_i Sᵀ`` after :func:`align_rotations_l2`.

    This is the metric of the paper's tables (eq:rotationerrorcalculate) and of the Strecha README.
    Returns ``(errors_deg (n,), S)``.
    """
    R_est = np.asarray(R_est, dtype=float).reshape(-1, 3, 3)
    R_gt = np.asarray(R_gt, dtype=float).reshape(-1, 3, 3)
    S = align_rotations_l2(R_est, R_gt)
    errors = np.degrees(so3.geodesic_angle(R_gt, R_est @ S.T))
    return errors, S


def relative_rotation_errors(R_est: np.ndarray, R_gt: np.ndarray, max_block: int = 500_000) -> np.ndarray:
    """Geodesic error (deg) of every relative rotation ``R_j R_iᵀ`` (i < j); gauge-free.

    Returned in ``np.triu_indices(n, 1)`` order (see :func:`pair_from_flat_index`). With
    ``Q_k = R_gt_kᵀ R_est_k``, ``R_ij_gtᵀ R_ij_est`` is conjugate to ``Q_iᵀ Q_j``, so the angle is
    that of ``Q_iᵀ Q_j``; rows are processed in blocks of about ``max_block`` pairs so thousands of
    cameras (millions of pairs) do not need (pairs, 3, 3) temporaries.
    """
    R_est = np.asarray(R_est, dtype=float).reshape(-1, 3, 3)
    R_gt = np.asarray(R_gt, dtype=float).reshape(-1, 3, 3)
    n = R_est.shape[0]
    Q = np.swapaxes(R_gt, -1, -2) @ R_est
    errors = np.empty(n * (n - 1) // 2)
    rows_per_block = max(1, max_block // max(n, 1))
    offset = 0
    for first in range(0, n - 1, rows_per_block):
        i, j = _block_pairs(n, first, min(n - 1, first + rows_per_block))
        errors[offset:offset + len(i)] = np.degrees(so3.geodesic_angle(Q[i], Q[j]))
        offset += len(i)
    return errors


def _block_pairs(n: int, first_row: int, end_row: int) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) with first_row <= i < end_row, i < j < n, in triu order."""
    counts = n - 1 - np.arange(first_row, end_row)
    i = np.repeat(np.arange(first_row, end_row), counts)
    starts = np.cumsum(counts) - counts
    j = np.arange(counts.sum()) - np.repeat(starts, counts) + i + 1
    return i, j


def pair_from_flat_index(n: int, flat: np.ndarray) -> np.ndarray:
    """(m, 2) pairs (i, j) of flat indices into the ``np.triu_indices(n, 1)`` order."""
    flat = np.asarray(flat, dtype=np.int64)
    row_starts = np.concatenate([[0], np.cumsum(n - 1 - np.arange(n - 1))])
    i = np.searchsorted(row_starts, flat, side="right") - 1
    j = flat - row_starts[i] + i + 1
    return np.stack([i, j], axis=1)


def trace_over_3_angle_deg(M: np.ndarray) -> np.ndarray:
    """OpenMVG's ``R2D(getRotationMagnitude(M))``: ``acos(clamp(trace(M)/3, -1, 1))`` in degrees.

    NOT the geodesic angle (formats.md §3.6): for a rotation by θ it gives acos((1+2cosθ)/3).
    """
    M = np.asarray(M, dtype=float)
    cos_like = np.clip(np.trace(M, axis1=-2, axis2=-1) / 3.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos_like))
