"""Multi-view triangulation of all tracks at once (linear start + Gauss-Newton refinement).

Pure numpy. Conventions (architecture.md): ``R_i = R_cam_from_world``, centre ``c_i``,
``x_cam = R_i (X - c_i)``; observations are normalized image coordinates ``(x, y)`` (z = 1).

Steps (the paper triangulates with known poses after LiGT, seed §7 "Global Pipeline",
citing Hartley & Sturm 1995):

1. Linear least squares ("midpoint"/LinearLS): minimise Σ_k ‖(I − d_k d_kᵀ)(X − c_k)‖²
   over the rays with unit world directions ``d_k = R_kᵀ x_k / ‖x_k‖``. Normal equations
   are 3×3 per point, summed over observations with ``np.bincount`` (segment sums).
2. A few Gauss–Newton iterations on the reprojection error in normalized coordinates,
   again one batched 3×3 system per point; a step is kept per point only if it lowers
   that point's cost (otherwise the damping of that point grows, Levenberg style).
3. Rejection: any depth ≤ ``min_depth`` (behind a camera), mean reprojection error above
   ``max_reprojection_error`` (normalized units: pixels / focal length, e.g. 4e-3 ≈ 4 px at
   f = 1000), or a maximum angle between the rays of the track below
   ``min_parallax_deg``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.geometry.tracks import pairs_in_track_chunks, segment_indices, segment_sums
from rotonly_cli.options import TriangulationOptions

__all__ = ["TriangulationOptions", "TriangulationResult", "triangulate_tracks", "max_ray_angle_deg"]


@dataclass
class TriangulationResult:
    points_in_world: np.ndarray  # (N, 3); NaN where the track had < 2 usable rays
    valid: np.ndarray  # (N,) bool: passed depth, reprojection and parallax tests
    mean_reprojection_error: np.ndarray  # (N,) normalized units
    max_parallax_deg: np.ndarray  # (N,) max angle between two rays of the track (NaN: not computed)
    in_front: np.ndarray  # (N,) bool: positive depth in every camera


def _solve_symmetric_3x3(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched solve of symmetric 3x3 systems by the adjugate (closed form, no per-matrix
    LAPACK call). ``A`` is (6, N): the entries 00, 01, 02, 11, 12, 22; ``b`` is (3, N).
    Rows whose matrix is singular relative to its size (|det| <= 1e-14 trace³) get NaN.
    Returns (x (3, N), ok (N,))."""
    a00, a01, a02, a11, a12, a22 = A
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    scale = (a00 + a11 + a22) ** 3
    ok = np.isfinite(det) & (np.abs(det) > 1e-14 * np.maximum(np.abs(scale), 1e-300))
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), np.nan)
    b0, b1, b2 = b
    x = np.stack([(c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
                  (c01 * b0 + c11 * b1 + c12 * b2) * inv_det,
                  (c02 * b0 + c12 * b1 + c22 * b2) * inv_det])
    return x, ok


def _rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-observation R @ v in component-major form: R (3, 3, N), v (3, N) -> (3, N)."""
    return R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2]


#: index pairs (a, b), a <= b, of the 6 entries of a symmetric 3x3 matrix, in the order
#: _solve_symmetric_3x3 takes them
_SYMMETRIC_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: observations triangulated at once (whole points; ~300 B of temporaries per observation)
CHUNK_OBSERVATIONS = 1 << 19


def _outer_entries(*vectors: np.ndarray) -> np.ndarray:
    """The 6 entries (_SYMMETRIC_ENTRIES order) of Σ_v v vᵀ per observation, for
    component-major vectors (3, N) -> (6, N)."""
    return np.stack([sum(v[a] * v[b] for v in vectors) for a, b in _SYMMETRIC_ENTRIES])


def max_ray_angle_deg(world_rays: np.ndarray, offsets: np.ndarray, max_views: int = 64) -> np.ndarray:
    """Per track the max angle (deg) between two unit rays; only the first ``max_views`` rays.
    The pairs of rays are taken a chunk of tracks at a time (tracks.pairs_in_track_chunks)."""
    length = np.diff(offsets)
    num_tracks = length.size
    capped_length = np.minimum(length, max_views)
    capped_offsets = np.zeros(num_tracks + 1, dtype=np.int64)
    np.cumsum(capped_length, out=capped_offsets[1:])
    # the first max_views rays of every track
    rays = world_rays[segment_indices(np.asarray(offsets[:-1], dtype=np.int64), capped_length)]
    min_cos = np.full(num_tracks, 1.0)
    for t0, t1, a, b in pairs_in_track_chunks(capped_offsets):
        cos_angle = np.clip(np.einsum("ij,ij->i", rays[a], rays[b]), -1.0, 1.0)
        # pairs are grouped by track: per-track minimum cosine with reduceat
        pair_count = capped_length[t0:t1] * (capped_length[t0:t1] - 1) // 2
        pair_start = np.cumsum(pair_count) - pair_count
        has_pair = np.flatnonzero(pair_count > 0)
        if has_pair.size:
            min_cos[t0 + has_pair] = np.minimum.reduceat(cos_angle, pair_start[has_pair])
    return np.degrees(np.arccos(min_cos))


def triangulate_tracks(R_cam_from_world: np.ndarray, centers: np.ndarray, obs_point: np.ndarray,
                       obs_view: np.ndarray, obs_xy: np.ndarray, num_points: int | None = None,
                       options: TriangulationOptions | None = None, with_parallax: bool = True) -> TriangulationResult:
    """Triangulate every point from its observations, batched.

    Args:
        R_cam_from_world: (n, 3, 3) world -> camera rotations.
        centers: (n, 3) camera centres.
        obs_point: (N_obs,) point index per observation, sorted (non-decreasing), e.g.
            ``Tracks.track_id``.
        obs_view: (N_obs,) view index per observation.
        obs_xy: (N_obs, 2) normalized image coordinates.
        num_points: number of points (default ``obs_point.max() + 1``).
        with_parallax: False: no parallax (NaN), for callers that do not test it
            (``options.min_parallax_deg`` must then be 0).
    """
    options = options or TriangulationOptions()
    options.validate()
    R = np.asarray(R_cam_from_world, dtype=float)
    C = np.asarray(centers, dtype=float)
    obs_point = np.asarray(obs_point, dtype=np.int64)
    obs_view = np.asarray(obs_view, dtype=np.int64)
    obs_xy = np.asarray(obs_xy, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or C.shape != (R.shape[0], 3):
        raise InputError("R_cam_from_world must be (n, 3, 3) and centers (n, 3)", field="centers")
    if obs_xy.shape != (obs_point.shape[0], 2) or obs_view.shape != obs_point.shape:
        raise InputError("obs_point, obs_view (N_obs,) and obs_xy (N_obs, 2) disagree", field="obs_xy")
    if obs_point.size and np.any(np.diff(obs_point) < 0):
        raise InputError("obs_point must be sorted (observations grouped by point)", field="obs_point")
    if not with_parallax and options.min_parallax_deg > 0:
        raise InputError("with_parallax=False needs min_parallax_deg = 0", field="options")
    if num_points is None:
        num_points = int(obs_point.max()) + 1 if obs_point.size else 0
    # a wrecked pose set (a collapsed LiGT solve, a point at infinity) overflows here: those
    # points come out NaN / not solvable and are rejected below, so numpy's warnings would
    # only reach the user's terminal
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if obs_point.size <= CHUNK_OBSERVATIONS:
            return _triangulate(R, C, obs_point, obs_view, obs_xy, num_points, options, with_parallax)
        # points are independent: slices of whole points, each with its observations in the
        # same order, give the same numbers bit for bit, in ~300 B per observation of a slice
        # instead of all of them (2.5 GB at a 1000-view collection)
        offsets = np.concatenate([[0], np.cumsum(np.bincount(obs_point, minlength=num_points))])
        cuts = np.unique(np.searchsorted(offsets, np.arange(0, obs_point.size, CHUNK_OBSERVATIONS), side="right") - 1)
        bounds = np.append(cuts, num_points)
        pieces = [_triangulate(R, C, obs_point[offsets[p0]:offsets[p1]] - p0, obs_view[offsets[p0]:offsets[p1]],
                               obs_xy[offsets[p0]:offsets[p1]], int(p1 - p0), options, with_parallax)
                  for p0, p1 in zip(bounds[:-1], bounds[1:])]
        return TriangulationResult(*(np.concatenate([getattr(r, f.name) for r in pieces])
                                     for f in dataclasses.fields(TriangulationResult)))


def _triangulate(R: np.ndarray, C: np.ndarray, obs_point: np.ndarray, obs_view: np.ndarray, obs_xy: np.ndarray,
                 num_points: int, options: TriangulationOptions, with_parallax: bool = True) -> TriangulationResult:
    """triangulate_tracks on validated arrays."""
    counts = np.bincount(obs_point, minlength=num_points)
    offsets = np.zeros(num_points + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])

    # Component-major (3, N_obs) arrays: products of three-vectors written out per component
    # run ~4x faster than einsum over (N_obs, 3, 3) stacks.
    R_obs = np.ascontiguousarray(R.transpose(1, 2, 0))[:, :, obs_view]  # (3, 3, N_obs)
    C_obs = np.ascontiguousarray(C.T)[:, obs_view]  # (3, N_obs)
    x, y = obs_xy[:, 0], obs_xy[:, 1]
    rays = R_obs[0] * x + R_obs[1] * y + R_obs[2]  # R^T (x, y, 1): ray direction in world
    rays /= np.sqrt(rays[0] ** 2 + rays[1] ** 2 + rays[2] ** 2)

    # 1. linear LS: Σ (I - d dᵀ) X = Σ (I - d dᵀ) c
    A = -segment_sums(_outer_entries(rays), obs_point, num_points)
    A[[0, 3, 5]] += counts
    ray_dot_center = rays[0] * C_obs[0] + rays[1] * C_obs[1] + rays[2] * C_obs[2]
    b = segment_sums(C_obs - rays * ray_dot_center, obs_point, num_points)
    points, solvable = _solve_symmetric_3x3(A, b)  # (3, num_points)
    solvable &= counts >= 2

    # 2. Gauss-Newton (Levenberg damped per point) on normalized reprojection error
    def residual_and_camera_point(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_cam = _rotate(R_obs, P[:, obs_point] - C_obs)
        depth = p_cam[2]
        safe = np.where(np.abs(depth) > 1e-300, depth, 1e-300)
        return np.stack([p_cam[0] / safe - x, p_cam[1] / safe - y]), p_cam

    def point_cost(res: np.ndarray) -> np.ndarray:
        return np.bincount(obs_point, weights=res[0] ** 2 + res[1] ** 2, minlength=num_points)

    res, p_cam = residual_and_camera_point(np.where(solvable, points, 0.0))
    cost = point_cost(res)
    damping = np.full(num_points, 1e-6)
    for _ in range(options.num_refinement_iterations):
        z = p_cam[2]
        z = np.where(np.abs(z) > 1e-12, z, 1e-12)
        # rows of J = d(p_xy / p_z)/d p_cam · R: J0 = R0 / z - p_x R2 / z², J1 likewise
        inv_z = 1.0 / z
        J0 = R_obs[0] * inv_z + R_obs[2] * (-p_cam[0] * inv_z ** 2)
        J1 = R_obs[1] * inv_z + R_obs[2] * (-p_cam[1] * inv_z ** 2)
        JtJ = segment_sums(_outer_entries(J0, J1), obs_point, num_points)
        Jtr = segment_sums(J0 * res[0] + J1 * res[1], obs_point, num_points)
        JtJ[[0, 3, 5]] += damping * (JtJ[0] + JtJ[3] + JtJ[5]) / 3.0
        step, ok = _solve_symmetric_3x3(JtJ, -Jtr)
        ok &= solvable
        trial = np.where(ok, points + np.nan_to_num(step), points)
        new_res, new_p_cam = residual_and_camera_point(np.where(solvable, trial, 0.0))
        new_cost = point_cost(new_res)
        better = ok & (new_cost <= cost)
        points = np.where(better, trial, points)
        damping = np.where(better, damping * 0.1, damping * 10.0)
        cost = np.where(better, new_cost, cost)
        take_obs = better[obs_point]
        res = np.where(take_obs, new_res, res)
        p_cam = np.where(take_obs, new_p_cam, p_cam)
    depth = p_cam[2]
    points = points.T
    rays = np.ascontiguousarray(rays.T)
    res = res.T

    # 3. tests
    error = np.linalg.norm(res, axis=1)
    mean_error = np.bincount(obs_point, weights=error, minlength=num_points) / np.maximum(counts, 1)
    min_depth = np.full(num_points, np.inf)
    np.minimum.at(min_depth, obs_point, depth)
    in_front = solvable & (min_depth > options.min_depth)
    parallax = max_ray_angle_deg(rays, offsets, options.max_parallax_views) if with_parallax else \
        np.full(num_points, np.nan)
    valid = (in_front & (mean_error <= options.max_reprojection_error)
             & ((parallax >= options.min_parallax_deg) if with_parallax else True))
    points = np.where(solvable[:, None], points, np.nan)
    mean_error = np.where(solvable, mean_error, np.nan)
    return TriangulationResult(points, valid, mean_error, parallax, in_front)
