"""Centres of views LiGT left out, by resection with their rotations known.

LiGT positions the largest set of views that tracks of three or more views tie together
(geometry.ligt.rigid). Its robust rounds judge observations by one global solve, and when wrong
multi-view tracks bend that solve the few tracks of a weak link look like outliers and the
views beyond it lose their centre (docs/tuning.md "Resection of the views LiGT left out"). A
view whose rotation is known needs only its centre c: every keypoint x of a point X already
triangulated from positioned views gives, with the world bearing b = Rᵀ(x, 1) / ‖·‖, the linear
constraint (I - b bᵀ)(X - c) = 0, two equations per point. Two points fix c, so a seeded RANSAC
over pairs finds the centre that most of them agree with at a pixel threshold, and least
squares on its inliers (each weighted by 1 / depth², so that the residual is an angle, as the
image error is) refines it. Views are added one at a time, the best-supported first, and the
points re-triangulated with each.

Arrays in, arrays out; no I/O.
"""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry.tracks import compact_track_ids, in_tracks_of_two
from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks
from rotonly_cli.options import ResectionOptions


def _projectors(bearings: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors -> (..., 3, 3) projectors I - b bᵀ onto their orthogonal planes."""
    return np.eye(3) - bearings[..., :, None] * bearings[..., None, :]


def _weighted_centres(P: np.ndarray, PX: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """argmin_c Σ_k w_k ‖P_k (X_k - c)‖² for every row of weights (T, k): (T, 3); NaN where
    the points do not fix c (their bearings parallel)."""
    A = np.einsum("tk,kab->tab", weights, P)
    rhs = np.einsum("tk,ka->ta", weights, PX)
    centres = np.full(rhs.shape, np.nan)
    ok = np.abs(np.linalg.det(A)) > 1e-12 * np.maximum(np.einsum("taa->t", A), 1e-300) ** 3
    if ok.any():
        centres[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
    return centres


def reprojection_errors(R_cam_from_world: np.ndarray, centres: np.ndarray, points: np.ndarray,
                        xy: np.ndarray) -> np.ndarray:
    """(T, k) normalized reprojection errors of k points with keypoints xy (k, 2) for T
    candidate centres (T, 3) of one camera; inf behind it or for a NaN centre."""
    camera = np.einsum("ab,tkb->tka", R_cam_from_world, points[None] - centres[:, None])
    with np.errstate(all="ignore"):
        error = np.linalg.norm(camera[..., :2] / camera[..., 2:3] - xy[None], axis=2)
    error[~(camera[..., 2] > 0) | ~np.isfinite(error)] = np.inf
    return error


def resect_centre(R_cam_from_world: np.ndarray, points: np.ndarray, xy: np.ndarray, threshold: float,
                  options: ResectionOptions = ResectionOptions()) -> tuple[np.ndarray, np.ndarray]:
    """Centre of a camera with known rotation from points (k, 3) and their keypoints
    (k, 2, normalized), robustly (module docstring): (centre (3,), inlier mask (k,)), the
    centre NaN with fewer than two points. ``threshold``: normalized reprojection error."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    k = len(points)
    if k < 2:
        return np.full(3, np.nan), np.zeros(k, dtype=bool)
    rays = np.einsum("ba,kb->ka", R_cam_from_world, np.column_stack([xy, np.ones(k)]))
    P = _projectors(rays / np.linalg.norm(rays, axis=1, keepdims=True))
    PX = np.einsum("kab,kb->ka", P, points)
    rng = np.random.default_rng(options.seed)
    first = rng.integers(0, k, options.trials)
    second = (first + rng.integers(1, k, options.trials)) % k  # two different points
    weights = np.zeros((options.trials, k))
    weights[np.arange(options.trials), first] = weights[np.arange(options.trials), second] = 1.0
    candidates = _weighted_centres(P, PX, weights)
    agree = reprojection_errors(R_cam_from_world, candidates, points, xy) <= threshold
    best = int(np.argmax(agree.sum(axis=1)))
    centre, inliers = candidates[best], agree[best]
    for _ in range(options.refinements):
        if inliers.sum() < 2:
            break
        depth2 = np.sum((points - centre) ** 2, axis=1)
        refined = _weighted_centres(P, PX, np.where(inliers, 1.0 / np.maximum(depth2, 1e-300), 0.0)[None])[0]
        if not np.all(np.isfinite(refined)):
            break
        centre = refined
        inliers = reprojection_errors(R_cam_from_world, centre[None], points, xy)[0] <= threshold
    return centre, inliers


def resect_left_out_views(R_cam_from_world: np.ndarray, centres: np.ndarray, obs_track: np.ndarray,
                          obs_view: np.ndarray, obs_xy: np.ndarray, threshold: np.ndarray,
                          candidates: np.ndarray, options: ResectionOptions = ResectionOptions(),
                          triangulation: TriangulationOptions | None = None) -> tuple[np.ndarray, list[dict]]:
    """Centres for the ``candidates`` (view indices) that have none, one at a time (module
    docstring): the points are triangulated from the views with a centre (tracks sorted by
    ``obs_track``), every candidate resected, the one with most inliers kept if it passes
    ``options``, and again until none does. ``threshold`` (n,): each view's normalized
    inlier threshold. Returns (centres with the new ones, one report per view kept, in order:
    view index, points, inliers)."""
    triangulation = triangulation or TriangulationOptions()
    centres = np.array(centres, dtype=float)
    left = [int(v) for v in candidates if not np.all(np.isfinite(centres[v]))]
    observations_of = {view: np.flatnonzero(obs_view == view) for view in left}
    added: list[dict] = []
    num_tracks = int(obs_track.max()) + 1 if obs_track.size else 0
    while left:
        posed = np.all(np.isfinite(centres), axis=1)
        used = in_tracks_of_two(obs_track, posed[obs_view])
        if not used.any():
            break
        tracks_used, track_index = compact_track_ids(obs_track[used])
        solved = triangulate_tracks(R_cam_from_world, np.where(posed[:, None], centres, 0.0), track_index,
                                    obs_view[used], obs_xy[used], tracks_used.size, triangulation)
        point = np.full((num_tracks, 3), np.nan)
        point[tracks_used[solved.valid]] = solved.points_in_world[solved.valid]
        has_point = np.all(np.isfinite(point[obs_track]), axis=1)
        best = None
        for view in left:
            mine = observations_of[view][has_point[observations_of[view]]]
            if mine.size < options.min_inliers:
                continue
            centre, inliers = resect_centre(R_cam_from_world[view], point[obs_track[mine]], obs_xy[mine],
                                            float(threshold[view]), options)
            count = int(inliers.sum())
            if count >= options.min_inliers and count >= options.min_inlier_fraction * mine.size \
                    and np.all(np.isfinite(centre)) and (best is None or count > best[1]):
                best = (view, count, mine.size, centre)
        if best is None:
            break
        view, count, num_points, centre = best
        centres[view] = centre
        left.remove(view)
        added.append({"view": view, "points": int(num_points), "inliers": count})
    return centres, added
