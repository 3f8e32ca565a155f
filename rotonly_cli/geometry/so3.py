"""SO(3) helpers, batched over a leading axis: hat, exp, log, projection, geodesic angle.

Pure numpy; every function accepts a single element ``(3,)`` / ``(3, 3)`` or a batch
``(..., 3)`` / ``(..., 3, 3)``.
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-8


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix [w]x so that hat(w) @ v == cross(w, v)."""
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (3, 3), dtype=w.dtype)
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat` (uses the antisymmetric part)."""
    W = np.asarray(W)
    return 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2],
                           W[..., 0, 2] - W[..., 2, 0],
                           W[..., 1, 0] - W[..., 0, 1]], axis=-1)


def exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, exp([w]x); Taylor series for tiny angles."""
    w = np.asarray(w, dtype=float)
    theta2 = np.sum(w * w, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = hat(w)
    I = np.broadcast_to(np.eye(3), K.shape)
    return I + a[..., None, None] * K + b[..., None, None] * (K @ K)


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R (angle in [0, pi]); stable near 0 and near pi."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    Rb = R.reshape(-1, 3, 3)
    cos_t = np.clip((np.trace(Rb, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0)
    theta = np.arccos(cos_t)
    v = vee(Rb)  # = sin(theta) * axis
    out = np.empty((Rb.shape[0], 3))
    sin_t = np.sin(theta)
    regular = theta < np.pi - 1e-4
    small = theta < 1e-6
    # regular branch: w = theta / sin(theta) * v ; series near 0
    factor = np.where(small, 1.0 + theta ** 2 / 6.0, theta / np.where(regular & ~small, sin_t, 1.0))
    out[regular] = factor[regular, None] * v[regular]
    # near pi: axis from the symmetric part (R + I)/2 = axis axis^T (1 - cos) + cos I ...
    near_pi = ~regular
    if np.any(near_pi):
        B = 0.5 * (Rb[near_pi] + np.transpose(Rb[near_pi], (0, 2, 1)))
        c = cos_t[near_pi]
        A = (B - c[:, None, None] * np.eye(3)) / (1.0 - c)[:, None, None]  # ~ axis axis^T
        k = np.argmax(np.diagonal(A, axis1=1, axis2=2), axis=1)
        axis = A[np.arange(len(k)), k]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        # fix the sign with the antisymmetric part (sin(theta) * axis)
        sign = np.sign(np.sum(axis * v[near_pi], axis=1))
        sign[sign == 0] = 1.0
        out[near_pi] = axis * (sign * theta[near_pi])[:, None]
    return out[0] if single else out.reshape(R.shape[:-2] + (3,))


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to M via SVD, det fixed to +1."""
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vt


def geodesic_angle(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle (rad) of R_a^T R_b, the paper's eq:rotationerrorcalculate, clipped to [0, pi]."""
    R_a = np.asarray(R_a, dtype=float)
    R_b = np.asarray(R_b, dtype=float)
    tr = np.einsum("...ji,...ji->...", R_a, R_b)  # trace(R_a^T R_b)
    cos_t = np.clip((tr - 1.0) * 0.5, -1.0, 1.0)
    # arccos is ill-conditioned near 0: use the chordal norm there
    angle = np.arccos(cos_t)
    small = angle < 1e-3
    if np.any(small):
        chord = np.linalg.norm(np.swapaxes(R_a, -1, -2) @ R_b - np.eye(3), axis=(-2, -1))
        angle = np.where(small, 2.0 * np.arcsin(np.clip(chord / (2.0 * np.sqrt(2.0)), 0.0, 1.0)), angle)
    return angle


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """True where R is orthonormal with det +1 (to ``tol``)."""
    R = np.asarray(R, dtype=float)
    if R.shape[-2:] != (3, 3):
        return np.zeros(R.shape[:-2], dtype=bool)
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
    return (err < tol) & (np.abs(np.linalg.det(R) - 1.0) < tol) & np.all(np.isfinite(R), axis=(-2, -1))


def random_rotations(n: int, rng: np.random.Generator, max_angle: float | None = None) -> np.ndarray:
    """Uniform random rotations, or rotations with uniform random axis and angle <= max_angle."""
    if max_angle is None:
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        w, x, y, z = q.T
        return np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ], axis=1)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0.0, max_angle, size=n)
    return exp(axis * angle[:, None])
