"""OpenMVG camera models: the forward distortion model and OpenMVG's own iterative
undistortion (formats.md §1.4), and the pixel convention at the file boundary."""

from __future__ import annotations

import os

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.scene.types import Intrinsics

PathLike = str | os.PathLike


PIXEL_OFFSET = 0.5  # COLMAP pixel = OpenMVG pixel + 0.5

# OpenMVG intrinsic types we model: polymorphic name -> (distortion field, its length)
# (formats.md §1.4; [MVG] Camera_*_io.hpp).
INTRINSIC_DISTORTION_FIELDS: dict[str, tuple[str | None, int]] = {
    "pinhole": (None, 0),
    "pinhole_radial_k1": ("disto_k1", 1),
    "pinhole_radial_k3": ("disto_k3", 3),
    "pinhole_brown_t2": ("disto_t2", 5),
    "fisheye": ("fisheye", 4),
}


# ============================================================================ pixel convention

def to_openmvg_pixels(pixels_colmap: np.ndarray) -> np.ndarray:
    """COLMAP -> OpenMVG pixel convention (-0.5), canonicalised so that a write->read->write
    cycle is byte-identical: ``q`` is iterated to a fixed point of q -> (q + 0.5) - 0.5, which
    floating point reaches after at most a couple of steps (only values whose +0.5 crosses a
    binade boundary move at all)."""
    q = np.asarray(pixels_colmap, dtype=np.float64) - PIXEL_OFFSET
    for _ in range(4):
        q_next = (q + PIXEL_OFFSET) - PIXEL_OFFSET
        if np.array_equal(q_next, q):
            break
        q = q_next
    return q


def to_colmap_pixels(pixels_openmvg: np.ndarray) -> np.ndarray:
    return np.asarray(pixels_openmvg, dtype=np.float64) + PIXEL_OFFSET


# ============================================================================ camera models

def check_model(intrinsics: Intrinsics) -> tuple[float, np.ndarray, np.ndarray]:
    """Return (focal, principal point (COLMAP convention), distortion) of an OpenMVG model."""
    if intrinsics.model not in INTRINSIC_DISTORTION_FIELDS:
        raise InputError(
            f"unsupported OpenMVG intrinsic type {intrinsics.model!r} "
            f"(known: {', '.join(INTRINSIC_DISTORTION_FIELDS)})",
            field=f"intrinsics[{intrinsics.id}].model")
    _, num_distortion = INTRINSIC_DISTORTION_FIELDS[intrinsics.model]
    params = np.asarray(intrinsics.params, dtype=np.float64).ravel()
    if params.size != 3 + num_distortion:
        raise InputError(
            f"{intrinsics.model} needs {3 + num_distortion} params [focal, ppx, ppy, k...], "
            f"got {params.size}", field=f"intrinsics[{intrinsics.id}].params")
    return float(params[0]), params[1:3], params[3:]


def _radial_disto_functor(k: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Squared distorted radius as a function of the squared undistorted one:
    r2 (1 + k1 r2 + k2 r2^2 + k3 r2^3)^2 ([MVG] Camera_Pinhole_Radial.cpp distoFunctor)."""
    poly = np.zeros_like(r2)
    for coefficient in k[::-1]:  # Horner: k1 + r2 (k2 + r2 k3)
        poly = coefficient + r2 * poly
    return r2 * np.square(1.0 + r2 * poly)


def _bisection_radius_solve(k: np.ndarray, r2_target: np.ndarray,
                            epsilon: float = 1e-10) -> np.ndarray:
    """Vectorised ``radial_distortion::bisection_Radius_Solve`` ([MVG] Camera_Pinhole_Radial.cpp):
    grow the bracket by factors of 1.05, then bisect until it is narrower than ``epsilon``.
    Each element follows exactly OpenMVG's scalar sequence (masked updates)."""
    lower = r2_target.copy()
    upper = r2_target.copy()
    for _ in range(2000):  # 1.05^2000 ~ 1e42: ample for any sane distortion
        shrink = _radial_disto_functor(k, lower) > r2_target
        if not shrink.any():
            break
        lower[shrink] /= 1.05
    for _ in range(2000):
        grow = _radial_disto_functor(k, upper) < r2_target
        if not grow.any():
            break
        upper[grow] *= 1.05
    for _ in range(200):  # each step halves the bracket: 200 steps cover any double range
        active = epsilon < upper - lower
        if not active.any():
            break
        mid = 0.5 * (lower + upper)
        above = _radial_disto_functor(k, mid) > r2_target
        upper = np.where(active & above, mid, upper)
        lower = np.where(active & ~above, mid, lower)
    return 0.5 * (lower + upper)


def _newton_polish_radius(k: np.ndarray, r2_target: np.ndarray,
                          r2_estimate: np.ndarray) -> np.ndarray:
    """Two Newton steps on OpenMVG's own equation D(s) = r2_target, started from its bisection
    result. The bisection stops at an *absolute* 1e-10 bracket on r^2, i.e. a relative error
    of ~1e-6 near the image centre (r ~ 0.01); the polish solves the same equation to machine
    precision and stays within OpenMVG's bracket. Steps that would not reduce the residual
    (non-monotone D) are not taken."""
    s = r2_estimate
    for _ in range(2):
        poly = np.zeros_like(s)  # P(s) = k1 + s k2 + s^2 k3 and its derivative
        poly_derivative = np.zeros_like(s)
        for coefficient in k[::-1]:
            poly_derivative = poly + s * poly_derivative
            poly = coefficient + s * poly
        factor = 1.0 + s * poly
        residual = s * factor * factor - r2_target
        derivative = factor * factor + 2.0 * s * factor * (poly + s * poly_derivative)
        with np.errstate(divide="ignore", invalid="ignore"):
            candidate = np.where(derivative > 0, s - residual / np.where(
                derivative > 0, derivative, 1.0), s)
        better = np.abs(_radial_disto_functor(k, candidate) - r2_target) <= np.abs(residual)
        s = np.where(better, candidate, s)
    return s


def _brown_displacement(k1: float, k2: float, k3: float, t1: float, t2: float,
                        points: np.ndarray) -> np.ndarray:
    """Brown-Conrady displacement (x_d - x) ([MVG] Camera_Pinhole_Brown.cpp distoFunction;
    t1 = OpenCV p1, t2 = OpenCV p2)."""
    x, y = points[:, 0], points[:, 1]
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    dx = x * radial + t2 * (r2 + 2.0 * x * x) + 2.0 * t1 * x * y
    dy = y * radial + t1 * (r2 + 2.0 * y * y) + 2.0 * t2 * x * y
    return np.stack([dx, dy], axis=1)


def _add_radial(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    r2 = np.einsum("ij,ij->i", points, points)
    coefficient = np.ones_like(r2)
    r_power = np.ones_like(r2)
    for k in distortion:  # 1 + k1 r^2 + k2 r^4 + k3 r^6
        r_power = r_power * r2
        coefficient = coefficient + k * r_power
    return points * coefficient[:, None]


def _add_fisheye(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    # theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8), theta = atan(r); identity for
    # r <= 1e-8 ([MVG] Camera_Pinhole_Fisheye.cpp add_disto).
    r = np.hypot(points[:, 0], points[:, 1])
    theta = np.arctan(r)
    theta2 = theta * theta
    theta_d = theta * (1.0 + theta2 * (distortion[0] + theta2 * (
        distortion[1] + theta2 * (distortion[2] + theta2 * distortion[3]))))
    scale = np.ones_like(r)
    far = r > 1e-8
    scale[far] = theta_d[far] / r[far]
    return points * scale[:, None]


def _remove_radial(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    r2 = np.einsum("ij,ij->i", points, points)
    scale = np.ones_like(r2)
    nonzero = r2 != 0
    if nonzero.any():
        k = np.asarray(distortion, dtype=np.float64)
        r2_undistorted = _newton_polish_radius(
            k, r2[nonzero], _bisection_radius_solve(k, r2[nonzero]))
        scale[nonzero] = np.sqrt(r2_undistorted / r2[nonzero])
    return points * scale[:, None]


def _remove_brown(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    undistorted = points.copy()
    displacement = _brown_displacement(*distortion, undistorted)
    active = np.abs(undistorted + displacement - points).sum(axis=1) > 1e-10
    for _ in range(1000):  # OpenMVG loops unbounded; 1000 only guards divergence
        if not active.any():
            break
        undistorted[active] = points[active] - displacement[active]
        displacement[active] = _brown_displacement(*distortion, undistorted[active])
        active[active] = np.abs(undistorted[active] + displacement[active]
                                - points[active]).sum(axis=1) > 1e-10
    return undistorted


def _remove_fisheye(points: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    theta_d = np.hypot(points[:, 0], points[:, 1])
    scale = np.ones_like(theta_d)
    far = theta_d > 1e-8
    if far.any():
        k1, k2, k3, k4 = distortion
        theta = theta_d[far].copy()
        for _ in range(10):  # exactly OpenMVG's 10 fixed-point steps
            theta2 = theta * theta
            theta = theta_d[far] / (1.0 + theta2 * (k1 + theta2 * (k2 + theta2 * (
                k3 + theta2 * k4))))
        scale[far] = np.tan(theta) / theta_d[far]
    return points * scale[:, None]


#: per OpenMVG intrinsic type: (add_disto, remove_disto) on (n, 2) normalized coordinates
_DISTORTION = {
    "pinhole": (lambda points, _: points.copy(), lambda points, _: points.copy()),
    "pinhole_radial_k1": (_add_radial, _remove_radial),
    "pinhole_radial_k3": (_add_radial, _remove_radial),
    "pinhole_brown_t2": (lambda points, d: points + _brown_displacement(*d, points), _remove_brown),
    "fisheye": (_add_fisheye, _remove_fisheye),
}


def _distortion_functions(model: str):
    if model not in _DISTORTION:
        raise InputError(f"unsupported OpenMVG intrinsic type {model!r}", field="model")
    return _DISTORTION[model]


def add_distortion(model: str, distortion: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """OpenMVG ``add_disto`` on (n, 2) undistorted normalized coordinates."""
    points = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
    return _distortion_functions(model)[0](points, distortion)


def remove_distortion(model: str, distortion: np.ndarray, distorted: np.ndarray) -> np.ndarray:
    """OpenMVG ``remove_disto`` on (n, 2) distorted normalized coordinates, with OpenMVG's own
    iterations: bisection on r^2 (radial, then polished to machine precision, see
    ``_newton_polish_radius``), fixed point on the displacement (Brown, stop at L1 residual
    <= 1e-10), exactly 10 fixed-point steps on theta (fisheye: like OpenMVG, not converged for
    strong distortion near the image border)."""
    points = np.asarray(distorted, dtype=np.float64).reshape(-1, 2)
    return _distortion_functions(model)[1](points, distortion)


def undistort_normalize(intrinsics: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(n, 2) pixels (COLMAP convention) -> (n, 2) undistorted normalized coordinates (z = 1),
    OpenMVG's ``remove_disto(ima2cam(p))``. The 0.5 pixel shifts of keypoints and principal
    point cancel, so this equals OpenMVG on its own pixels."""
    focal, principal_point, distortion = check_model(intrinsics)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    distorted = (pixels - principal_point) / focal
    return remove_distortion(intrinsics.model, distortion, distorted)


def distort_project(intrinsics: Intrinsics, normalized: np.ndarray) -> np.ndarray:
    """(n, 2) undistorted normalized coordinates -> (n, 2) pixels (COLMAP convention),
    OpenMVG's forward model ``cam2ima(add_disto(x))``."""
    focal, principal_point, distortion = check_model(intrinsics)
    distorted = add_distortion(intrinsics.model, distortion, normalized)
    return distorted * focal + principal_point
