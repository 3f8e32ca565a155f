"""LiGT: linear global translation from known rotations and tracks (Cai et al., TPAMI 2023).

Pure numpy/scipy, the paper/OpenMVG form of algorithms.md §1.1–1.2, batched over all
tracks. Conventions: ``R_i = R_cam_from_world``, ``t_i`` = camera **centre**; normalized
observations ``x = (x, y, 1)``.

Per track k with views V_k:

* base views ``(l, r) = argmax_{a<b} ‖θ_ab‖``, ``θ_lr = [x_r]_× R_lr x_l`` (TPAMI eq. 29;
  OpenMVG ``SelectBaseViews`` scans a < b in track order and keeps the first maximum).
  ``‖θ_ab‖ = ‖(R_bᵀ x_b) × (R_aᵀ x_a)‖`` so it is computed on world rays.
* ``a_lrᵀ = ([R_lr x_l]_× x_r)ᵀ [x_r]_×``.
* for every other view i ≠ l (i = r included): ``B t_r + C t_i + D t_l = 0`` with
  ``B = [x_i]_× R_li x_l a_lrᵀ R_r``, ``C = ‖θ_lr‖² [x_i]_× R_i``, ``D = −(B + C)``.

``LᵀL`` (3n × 3n) is accumulated chunk by chunk from the constraints' 3 × 9 blocks
``M = [B | C | D]``: each ``MᵀM`` is a few outer products of 3-vectors, summed per view triple
(r, i, l) and then per 3 × 3 block of LᵀL (L itself is never formed). Gauge: the centroid of the
solved centres is 0 and their norm 1, i.e. the eigenvector of the smallest eigenvalue of LᵀL
orthogonal to the three common translations (its null space; dense ``eigh`` for small
problems, shift-invert ``eigsh`` with those translations projected out otherwise). OpenMVG and
pyTheia fix one view's centre at 0 instead; under a unit norm that favours configurations far
from that view, and a weakly linked gauge view then keeps its distance while every other centre
shrinks around one point (algorithms.md §1.2). Only the largest **rigid** set of views is
solved (:func:`rigid_views`): views whose distance to the others no track of three or more
views fixes get no centre. Sign: chirality vote ``a_lrᵀ R_r (t_l − t_r) > 0``
per track (TPAMI "Step 5", OpenMVG ``IdentifySign``).

**Output scale**: centres are returned translated so the centroid of the solved centres is
0 and scaled so their mean distance to that centroid is 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, eigsh, splu

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.geometry.baselines import baseline_disagreement_deg, views_off_their_baselines  # noqa: F401 (re-exported)
from rotonly_cli.geometry.rigid_views import rigid_views
from rotonly_cli.geometry.so3 import hat
from rotonly_cli.geometry.tracks import (
    EVALUATION_PARTS,
    compact_track_ids,
    even_ranges,
    in_tracks_of_two,
    pairs_in_track_chunks,
    segment_indices,
    segment_sums,
    track_starts,
)
from rotonly_cli.options import LiGTOptions

__all__ = ["LiGTOptions", "LiGTResult", "RobustLiGTResult", "ligt_translations", "ligt_normal_matrix",
           "observation_errors", "outlier_threshold_px", "robust_ligt_translations"]


@dataclass
class LiGTResult:
    centers: np.ndarray  # (n, 3) camera centres; NaN for views without constraints
    has_translation: np.ndarray  # (n,) bool: view was solved
    smallest_eigenvalues: np.ndarray  # smallest (and second, if computed) eigenvalues of LᵀL
    num_constraints_per_view: np.ndarray  # (n,) constraint blocks touching the view
    num_tracks_used: int
    sign_votes: tuple[int, int]  # (positive, negative) chirality votes after the sign fix


def _select_base_views(world_rays: np.ndarray, offsets: np.ndarray,
                       max_views: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per track the observation indices (l, r) with max ‖θ‖, and that norm (the pairs of
    the first ``max_views`` observations, a chunk of tracks at a time)."""
    length = np.diff(offsets)
    num_tracks = length.size
    capped_length = np.minimum(length, max_views)
    use = segment_indices(offsets[:-1], capped_length)
    capped = np.zeros(num_tracks + 1, dtype=np.int64)
    np.cumsum(capped_length, out=capped[1:])
    base_l = np.full(num_tracks, -1, dtype=np.int64)
    base_r = np.full(num_tracks, -1, dtype=np.int64)
    best_norm = np.zeros(num_tracks)
    for t0, t1, a, b in pairs_in_track_chunks(capped):
        a, b = use[a], use[b]
        theta_norm = np.linalg.norm(np.cross(world_rays[b], world_rays[a]), axis=1)
        # pairs come grouped by track (pairs_within_tracks order): per-track max by reduceat,
        # then the first pair reaching it (OpenMVG keeps the first maximum of its a<b scan)
        pair_count = capped_length[t0:t1] * (capped_length[t0:t1] - 1) // 2
        has_pair = np.flatnonzero(pair_count > 0)
        if has_pair.size == 0:
            continue
        chunk_norm = np.zeros(t1 - t0)
        chunk_norm[has_pair] = np.maximum.reduceat(theta_norm, (np.cumsum(pair_count) - pair_count)[has_pair])
        pair_track = np.repeat(np.arange(t1 - t0), pair_count)
        best_norm[t0:t1] = chunk_norm
        reaching = np.flatnonzero(theta_norm == chunk_norm[pair_track])
        if not reaching.size:  # every norm NaN
            continue
        first = reaching[np.r_[True, pair_track[reaching][1:] != pair_track[reaching][:-1]]]
        base_l[t0 + pair_track[first]] = a[first]
        base_r[t0 + pair_track[first]] = b[first]
    return base_l, base_r, best_norm


def _sum_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted unique keys, the sum of ``values`` rows per key)."""
    if not keys.size:
        return keys, values
    order = np.argsort(keys)
    sorted_keys = keys[order]
    is_first = np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]
    group = np.empty(keys.size, dtype=np.int64)
    group[order] = np.cumsum(is_first) - 1
    num_groups = int(is_first.sum())
    # one bincount per value component: much faster than reduceat over short segments
    sums = segment_sums(np.ascontiguousarray(values.reshape(keys.size, -1).T), group, num_groups)
    return sorted_keys[is_first], sums.T.reshape(-1, *values.shape[1:])


def _constraint_grams(x_i: np.ndarray, y_i: np.ndarray, R_i: np.ndarray, y_l: np.ndarray,
                      sign_row: np.ndarray, theta_sq: np.ndarray, col_view: np.ndarray,
                      num_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Σ M_kᵀ M_k of the constraints' 3 × 9 row blocks ``M_k = [B | C | D]``, summed over the
    constraints that share a view triple (r, i, l): (unique triples (G, 3), (G, 3, 3, 3, 3)
    Gram blocks [row block, column block, row, column]).

    The blocks need no 3 × 9 product per constraint. ``B = u vᵀ`` is rank one
    (``u = [x_i]_× R_i y_l`` with the base view's world ray ``y_l = R_lᵀ x_l``,
    ``vᵀ = a_lrᵀ R_r``) and ``C = ‖θ_lr‖² [x_i]_× R_i``, so
    ``BᵀB = ‖u‖² v vᵀ``, ``BᵀC = v wᵀ`` with ``wᵀ = uᵀ C = −‖θ_lr‖² (x_i × u)ᵀ R_i``, and
    ``CᵀC = ‖θ_lr‖⁴ (‖x_i‖² I − y yᵀ)`` with the world ray ``y = R_iᵀ x_i``. These 27 numbers
    are summed per triple first; ``D = −(B + C)`` gives the other blocks from the sums.
    """
    u = np.cross(x_i, np.einsum("nij,nj->ni", R_i, y_l))
    v = sign_row
    w = -theta_sq[:, None] * np.einsum("ni,nij->nj", np.cross(x_i, u), R_i)
    theta_4 = theta_sq ** 2
    num = x_i.shape[0]
    terms = np.empty((num, 3, 3, 3))  # [BᵀB, BᵀC, CᵀC]
    terms[:, 0] = (np.einsum("ni,ni->n", u, u)[:, None] * v)[:, :, None] * v[:, None, :]
    terms[:, 1] = v[:, :, None] * w[:, None, :]
    terms[:, 2] = -(theta_4[:, None] * y_i)[:, :, None] * y_i[:, None, :]
    terms[:, 2, [0, 1, 2], [0, 1, 2]] += (theta_4 * np.einsum("ni,ni->n", x_i, x_i))[:, None]
    triple, sums = _sum_by_key((col_view[:, 0] * num_views + col_view[:, 1]) * num_views + col_view[:, 2], terms)
    views = np.stack([triple // (num_views * num_views), triple // num_views % num_views, triple % num_views],
                     axis=1)
    BB, BC, CC = np.moveaxis(sums, 1, 0)
    CB = np.swapaxes(BC, 1, 2)
    BD, CD, DD = -(BB + BC), -(CB + CC), BB + BC + CB + CC
    gram = np.stack([np.stack([BB, BC, BD], axis=1),
                     np.stack([CB, CC, CD], axis=1),
                     np.stack([np.swapaxes(BD, 1, 2), np.swapaxes(CD, 1, 2), DD], axis=1)], axis=1)
    return views, gram


def ligt_normal_matrix(R_cam_from_world: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray,
                       obs_xy: np.ndarray, num_views: int, options: LiGTOptions | None = None
                       ) -> tuple[sp.csr_matrix, dict[str, np.ndarray]]:
    """Assemble LᵀL (3n × 3n, CSR) and the per-track sign rows.

    Observations must be grouped by track (``obs_track`` non-decreasing). Returns the
    matrix and a dict with ``sign_l, sign_r`` (view of each used track's base pair),
    ``sign_row`` (T_used, 3) = ``a_lrᵀ R_r``, ``sign_track`` (T_used,) the track of each
    sign row and ``constraints_per_view`` (n,).
    """
    options = options or LiGTOptions()
    R = np.asarray(R_cam_from_world, dtype=float)
    obs_track = np.asarray(obs_track, dtype=np.int64)
    obs_view = np.asarray(obs_view, dtype=np.int64)
    x = np.concatenate([np.asarray(obs_xy, dtype=float), np.ones((len(obs_track), 1))], axis=1)
    num_tracks = int(obs_track.max()) + 1 if obs_track.size else 0
    counts = np.bincount(obs_track, minlength=num_tracks)
    offsets = np.zeros(num_tracks + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])

    world_rays = np.einsum("nji,nj->ni", R[obs_view], x)  # R_iᵀ x_i
    base_l, base_r, theta_norm = _select_base_views(world_rays, offsets, options.max_base_search_views)
    track_used = (base_l >= 0) & (theta_norm > options.min_base_theta_norm)

    # per used track: a_lrᵀ R_r (row), ‖θ_lr‖²
    tl, tr = base_l[track_used], base_r[track_used]
    view_l, view_r = obs_view[tl], obs_view[tr]
    R_r = R[view_r]
    R_lr_x_l = np.einsum("nij,nj->ni", R_r, world_rays[tl])  # R_r R_lᵀ x_l
    theta = np.cross(x[tr], R_lr_x_l)  # [x_r]_× R_lr x_l
    a_row = np.einsum("ni,nij->nj", np.cross(R_lr_x_l, x[tr]), hat(x[tr]))  # a_lrᵀ
    sign_row = np.einsum("ni,nij->nj", a_row, R_r)  # a_lrᵀ R_r
    theta_sq = np.einsum("ni,ni->n", theta, theta)

    # constraint rows: every observation i of a used track except its base l
    used_index = np.full(num_tracks, -1, dtype=np.int64)
    used_index[track_used] = np.arange(track_used.sum())
    obs_used = used_index[obs_track]
    is_constraint = obs_used >= 0
    is_constraint[base_l[track_used]] = False
    constraint_obs = np.flatnonzero(is_constraint)
    constraint_track = obs_used[constraint_obs]

    num_cols = 3 * num_views
    constraints_per_view = np.zeros(num_views, dtype=np.int64)
    block_keys, block_sums = [np.zeros(0, dtype=np.int64)], [np.zeros((0, 3, 3))]
    for start in range(0, constraint_obs.size, options.chunk_size):
        obs_i = constraint_obs[start:start + options.chunk_size]
        trk = constraint_track[start:start + options.chunk_size]
        col_view = np.stack([view_r[trk], obs_view[obs_i], view_l[trk]], axis=1)  # (K, 3): r, i, l
        views, gram = _constraint_grams(x[obs_i], world_rays[obs_i], R[obs_view[obs_i]], world_rays[tl[trk]],
                                        sign_row[trk], theta_sq[trk], col_view, num_views)
        # block (A, B) of a triple's Gram goes to the 3 × 3 block (views[A], views[B]) of LᵀL;
        # summed per block here (i = r and triples sharing views) and over the chunks below
        keys, sums = _sum_by_key((views[:, :, None] * num_views + views[:, None, :]).ravel(),
                                 gram.reshape(-1, 3, 3))
        block_keys.append(keys)
        block_sums.append(sums)
        constraints_per_view += np.bincount(col_view.ravel(), minlength=num_views)
    keys, sums = _sum_by_key(np.concatenate(block_keys), np.concatenate(block_sums))
    # keys are sorted: block rows ascending, columns ascending within a row (BSR order)
    indptr = np.zeros(num_views + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys // num_views, minlength=num_views), out=indptr[1:])
    LTL = sp.bsr_matrix((sums, keys % num_views, indptr), shape=(num_cols, num_cols)).tocsr()
    extras = {"sign_l": view_l, "sign_r": view_r, "sign_row": sign_row, "sign_track": np.flatnonzero(track_used),
              "constraints_per_view": constraints_per_view}
    return LTL, extras


def _smallest_eigenvector(matrix: sp.csr_matrix, options: LiGTOptions) -> tuple[np.ndarray, np.ndarray]:
    """The unit eigenvector of the smallest eigenvalue of ``matrix`` (the solved views' LᵀL,
    3m × 3m) orthogonal to the common translations, and the two smallest such eigenvalues.
    LᵀL is a sum over differences of centres, so those translations are its exact null space."""
    size = matrix.shape[0]
    gauge = np.kron(np.ones((size // 3, 1)), np.eye(3)) / np.sqrt(size // 3)  # orthonormal (3m, 3)
    if size <= options.max_dense_unknowns + 3:
        dense = matrix.toarray()
        # lift the null space above every other eigenvalue (the largest row sum bounds them)
        lift = 2.0 * float(np.abs(dense).sum(axis=1).max()) + 1.0
        values, vectors = np.linalg.eigh(dense + lift * (gauge @ gauge.T))
        return vectors[:, 0], values[: min(2, size - 3)]
    # shift slightly below 0 so (LᵀL − σI) is positive definite: the null space makes LᵀL singular
    sigma = -1e-8 * matrix.diagonal().mean()
    factor = splu((matrix - sigma * sp.identity(size, format="csr")).tocsc())

    def project(x: np.ndarray) -> np.ndarray:
        return x - gauge @ (gauge.T @ x)

    # (LᵀL − σI)⁻¹ with the translations projected out on both sides: they map to 0 and never
    # come out as the largest magnitudes of the shift-inverted problem
    inverse = LinearOperator((size, size), matvec=lambda x: project(factor.solve(project(np.ravel(x)))),
                             dtype=float)
    start = project(np.cos(np.arange(size, dtype=float)))
    values, vectors = eigsh(matrix, k=2, sigma=sigma, which="LM", OPinv=inverse, v0=start, tol=1e-12)
    order = np.argsort(values)
    return project(vectors[:, order[0]]), values[order]


def _validated(R_cam_from_world, obs_track, obs_view, obs_xy):
    R = np.asarray(R_cam_from_world, dtype=float)
    obs_track = np.asarray(obs_track, dtype=np.int64)
    obs_view = np.asarray(obs_view, dtype=np.int64)
    obs_xy = np.asarray(obs_xy, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise InputError("R_cam_from_world must be (n, 3, 3)", field="R_cam_from_world")
    if obs_view.shape != obs_track.shape or obs_xy.shape != (obs_track.size, 2):
        raise InputError("obs_track, obs_view (N_obs,) and obs_xy (N_obs, 2) disagree", field="obs_xy")
    if obs_track.size and np.any(np.diff(obs_track) < 0):
        raise InputError("obs_track must be sorted (observations grouped by track)", field="obs_track")
    return R, obs_track, obs_view, obs_xy


#: the per-track arrays of ligt_normal_matrix's extras (one entry per used track)
SIGN_KEYS = ("sign_l", "sign_r", "sign_row", "sign_track")


def _view_masked_normal_matrix(R: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray, obs_xy: np.ndarray,
                               view_mask: np.ndarray | None, options: LiGTOptions):
    """:func:`ligt_normal_matrix` of the observations in the views of ``view_mask``;
    ``obs_track`` any non-decreasing track ids (``sign_track`` is in those ids). None
    without observations."""
    if view_mask is not None:
        keep = np.asarray(view_mask, dtype=bool)[obs_view]
        obs_track, obs_view, obs_xy = obs_track[keep], obs_view[keep], obs_xy[keep]
    if not obs_track.size:
        return None
    tracks, compact = compact_track_ids(obs_track)
    LTL, extras = ligt_normal_matrix(R, compact, obs_view, obs_xy, R.shape[0], options)
    extras["sign_track"] = tracks[extras["sign_track"]]
    return LTL, extras


def _merged_normal_matrix(parts: list[tuple[sp.csr_matrix, dict]]) -> tuple[sp.csr_matrix, dict]:
    """LᵀL and the sign rows of disjoint sets of tracks, merged in the order given."""
    LTL = parts[0][0]
    for matrix, _ in parts[1:]:
        LTL = LTL + matrix
    extras = {key: np.concatenate([part[1][key] for part in parts]) for key in SIGN_KEYS}
    extras["constraints_per_view"] = np.sum([part[1]["constraints_per_view"] for part in parts], axis=0)
    return LTL, extras


def _solve_normal_matrix(LTL: sp.csr_matrix, extras: dict, view_mask: np.ndarray | None,
                         options: LiGTOptions) -> LiGTResult:
    """The centres from LᵀL: the solved views' block, centroid gauge, smallest eigenvector,
    chirality vote, normalisation."""
    num_views = LTL.shape[0] // 3
    constraints_per_view = extras["constraints_per_view"]
    solved = constraints_per_view >= max(options.min_constraints_per_view, 1)
    if view_mask is not None:
        solved &= np.asarray(view_mask, dtype=bool)
    if solved.sum() < 2:
        raise AlgorithmError(f"LiGT needs at least 2 constrained views, got {int(solved.sum())}")
    solved_views = np.flatnonzero(solved)
    cols = (3 * solved_views[:, None] + np.arange(3)).ravel()
    vector, eigenvalues = _smallest_eigenvector(LTL[cols][:, cols], options)

    translations = np.zeros((num_views, 3))
    translations[solved_views] = vector.reshape(-1, 3)
    # chirality vote: a_lrᵀ R_r (t_l − t_r) > 0 for every used track (algorithms.md §1.2)
    votes = np.einsum("ni,ni->n", extras["sign_row"],
                      translations[extras["sign_l"]] - translations[extras["sign_r"]])
    positive, negative = int((votes > 0).sum()), int((votes < 0).sum())
    if positive < negative:
        translations = -translations
        positive, negative = negative, positive
    centers = np.full((num_views, 3), np.nan)
    solved_centers = translations[solved]
    solved_centers = solved_centers - solved_centers.mean(axis=0)
    mean_distance = np.linalg.norm(solved_centers, axis=1).mean()
    if not np.isfinite(mean_distance) or mean_distance <= 0:
        raise AlgorithmError("LiGT solution collapsed to a single point")
    centers[solved] = solved_centers / mean_distance
    return LiGTResult(centers, solved, np.asarray(eigenvalues), constraints_per_view,
                      int(extras["sign_row"].shape[0]), (positive, negative))


def ligt_translations(R_cam_from_world: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray,
                      obs_xy: np.ndarray, view_mask: np.ndarray | None = None,
                      options: LiGTOptions | None = None) -> LiGTResult:
    """Camera centres from global rotations and tracks (LiGT, algorithms.md §1).

    Args:
        R_cam_from_world: (n, 3, 3) world -> camera rotations.
        obs_track: (N_obs,) track id per observation, non-decreasing (``Tracks.track_id``).
        obs_view: (N_obs,) view per observation (``Tracks.view``).
        obs_xy: (N_obs, 2) normalized coordinates.
        view_mask: (n,) bool; False views are ignored (their observations dropped).

    Views without any constraint (e.g. only pure-rotation tracks, or masked out) and views
    outside the largest rigid set (:func:`rigid_views`) are reported via
    ``has_translation = False`` with NaN centres.
    """
    options = options or LiGTOptions()
    R, obs_track, obs_view, obs_xy = _validated(R_cam_from_world, obs_track, obs_view, obs_xy)
    view_mask = rigid_views(obs_track, obs_view, R.shape[0], view_mask, options.max_base_search_views)
    normal = _view_masked_normal_matrix(R, obs_track, obs_view, obs_xy, view_mask, options)
    if normal is None:
        raise AlgorithmError("LiGT needs at least 2 constrained views, got 0")
    return _solve_normal_matrix(*normal, view_mask, options)


@dataclass
class RobustLiGTResult:
    result: LiGTResult  # the last solve
    keep: np.ndarray  # (N_obs,) bool: observations of that solve
    error_px: np.ndarray  # (N_obs,) reprojection error at the last solve (inf: no point / no centre)
    threshold_px: float  # outlier threshold of the last round (inf without rounds)
    rounds: list[dict]  # per round: observations used, sigma, threshold, dropped, re-admitted


#: Gauss-Newton steps of the points of :func:`observation_errors`: their errors decide drops at
#: a pixel or more, and with 2 (of the final triangulation's 5) every drop on the eight Strecha
#: inputs is the same (the written models are byte-identical); ~0.03 s of 0.13 s per call on
#: fountain-P11's 80 000 observations
ERROR_REFINEMENT_ITERATIONS = 2


def observation_errors(R: np.ndarray, centers: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray,
                       obs_xy: np.ndarray, used: np.ndarray, triangulate=None) -> np.ndarray:
    """Normalized reprojection error of every observation against its track's point,
    triangulated (linear + Gauss-Newton, no rejection) from the ``used`` observations of
    views with a centre; inf where the track has no point or the point lies behind the camera.
    ``triangulate``: triangulation.triangulate_tracks or a function of its arguments and result."""
    from rotonly_cli.geometry.triangulation import TriangulationOptions, triangulate_tracks

    posed = np.all(np.isfinite(centers), axis=1)
    used = in_tracks_of_two(obs_track, used & posed[obs_view])
    error = np.full(obs_track.size, np.inf)
    if not used.any():
        return error
    tracks_used, track_index = compact_track_ids(obs_track[used])
    # the points only serve an outlier test at a pixel: two Gauss-Newton steps from the
    # linear start (the final triangulation takes five) and no parallax
    loose = TriangulationOptions(max_reprojection_error=np.inf, min_parallax_deg=0.0,
                                 num_refinement_iterations=ERROR_REFINEMENT_ITERATIONS)
    C = np.where(posed[:, None], centers, 0.0)
    solved = (triangulate or triangulate_tracks)(R, C, track_index, obs_view[used], obs_xy[used],
                                tracks_used.size, loose, with_parallax=False)
    point = np.full((int(obs_track.max()) + 1, 3), np.nan)
    point[tracks_used] = solved.points_in_world
    X = point[obs_track]
    camera = np.einsum("nij,nj->ni", R[obs_view], X - C[obs_view])
    with np.errstate(all="ignore"):
        projected = camera[:, :2] / camera[:, 2:3]
        error = np.linalg.norm(projected - obs_xy, axis=1)
    error[~(camera[:, 2] > 0) | ~np.isfinite(error) | ~posed[obs_view]] = np.inf
    return error


def outlier_threshold_px(error_px: np.ndarray, options: LiGTOptions) -> tuple[float, float]:
    """(sigma, threshold) of reprojection errors (px, finite): sigma = 1.4826 x the median;
    threshold = max(outlier_sigmas x sigma, min_outlier_threshold_px, the error that keeps
    1 - max_drop_fraction of them)."""
    sigma = 1.4826 * float(np.median(error_px))
    threshold = max(options.outlier_sigmas * sigma, options.min_outlier_threshold_px,
                    float(np.quantile(error_px, 1.0 - options.max_drop_fraction)))
    return sigma, threshold


def _annealed_floor_px(round_number: int, options: LiGTOptions) -> float:
    """The robust rounds' pixel floor in round ``round_number`` (0 = after the first solve):
    ``outlier_threshold_start_px`` halved every round, down to ``min_outlier_threshold_px``."""
    start = options.outlier_threshold_start_px or options.min_outlier_threshold_px
    return max(options.min_outlier_threshold_px, start / 2.0 ** round_number)


class _TrackParts:
    """The robust rounds' work on contiguous parts of the tracks (observation ranges cut at
    track boundaries, about equal in observations): LᵀL of a part's used observations and the
    reprojection errors of its tracks. Part ``p`` of a round is :meth:`__call__` on
    ``(kind, p, args)``, here or in a helper process forked with this object."""

    def __init__(self, R: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray, obs_xy: np.ndarray,
                 view_mask: np.ndarray | None, options: LiGTOptions):
        self.R, self.obs_track, self.obs_view, self.obs_xy = R, obs_track, obs_view, obs_xy
        self.view_mask, self.options = view_mask, options
        bounds = np.append(track_starts(obs_track), obs_track.size)
        self.ranges = [(int(bounds[a]), int(bounds[b])) for a, b in even_ranges(np.diff(bounds), EVALUATION_PARTS)]

    def __call__(self, message):
        kind, part, args = message
        a, b = self.ranges[part]
        if kind == "normal":
            (used,) = args  # the part's slice
            return self.normal_matrix(used, a, b)
        centers, used = args
        return observation_errors(self.R, centers, self.obs_track[a:b], self.obs_view[a:b], self.obs_xy[a:b], used)

    def normal_matrix(self, used: np.ndarray, a: int = 0, b: int | None = None):
        """LᵀL and sign rows of the ``used`` observations of [a, b) (``used`` that slice), in
        the tracks' own ids; None without any."""
        b = self.obs_track.size if b is None else b
        return _view_masked_normal_matrix(self.R, self.obs_track[a:b][used], self.obs_view[a:b][used],
                                          self.obs_xy[a:b][used], self.view_mask, self.options)

    def evaluate(self, used: np.ndarray, centers: np.ndarray | None = None, peer=None) -> list:
        """Every part's result, in order, with the ``used`` observations (all of them): LᵀL,
        or with ``centers`` the errors. The parts after the first are evaluated by ``peer``
        (submitted first, so both run side by side) when there is one."""
        messages = [("normal", part, (used[a:b],)) if centers is None else ("errors", part, (centers, used[a:b]))
                    for part, (a, b) in enumerate(self.ranges)]
        if peer is not None and len(messages) > 1:
            peer.submit(messages[1:])
            return [self(messages[0])] + peer.collect()
        return [self(message) for message in messages]

    def serve(self, messages):
        """The helper's side of :meth:`evaluate`."""
        return [self(message) for message in messages]


def robust_ligt_translations(R_cam_from_world: np.ndarray, obs_track: np.ndarray, obs_view: np.ndarray,
                             obs_xy: np.ndarray, obs_focal_px: np.ndarray, view_mask: np.ndarray | None = None,
                             options: LiGTOptions | None = None, peer_class=None) -> RobustLiGTResult:
    """LiGT with outlier rejection by reprojection: solve, triangulate every track with the
    centres, and solve again without the observations whose error exceeds
    max(``outlier_sigmas`` x sigma, a floor) (sigma = 1.4826 x the median error in pixels,
    ``obs_focal_px`` per observation; the floor starts at ``outlier_threshold_start_px`` and
    halves every round down to ``min_outlier_threshold_px``). Each round judges every observation
    afresh (one dropped by a wrecked first solve comes back), drops at most
    ``max_drop_fraction`` of the used ones, and the rounds stop when the set settles.

    A wrong match along the epipolar line (repeated structure) is consistent in its own pair
    but not with the rest of its track, so it shows as a reprojection error once the centres
    are right; the linear solve itself weighs it like any other (docs/tuning.md).

    ``peer_class``: a helper process for the second half of the tracks (e.g.
    runtime.parallel.ForkedPeer: ``peer_class(handler)`` a context manager with submit /
    collect); None: one process. The numbers do not depend on it (``tracks.EVALUATION_PARTS``)."""
    options = options or LiGTOptions()
    R, obs_track, obs_view, obs_xy = _validated(R_cam_from_world, obs_track, obs_view, obs_xy)
    obs_focal_px = np.broadcast_to(np.asarray(obs_focal_px, dtype=float), obs_track.shape)
    parts = _TrackParts(R, obs_track, obs_view, obs_xy, view_mask, options)
    if peer_class is None or len(parts.ranges) < 2:
        return _robust_rounds(parts, obs_focal_px, view_mask, options, None)
    with peer_class(parts.serve) as peer:
        return _robust_rounds(parts, obs_focal_px, view_mask, options, peer)


#: a round's LᵀL is updated from the last one's when the tracks whose observations changed hold
#: at most this fraction of the used observations, else assembled afresh
MAX_UPDATED_FRACTION = 0.25


def _updated_normal_matrix(parts: _TrackParts, assembled, used: np.ndarray, peer):
    """LᵀL and sign rows of the ``used`` observations: assembled by the parts, or, when the
    last round's ``assembled = (used, normal)`` differs in a few tracks only, that one with
    those tracks' old terms taken out and their new ones added (LᵀL is a sum over tracks, each
    with base views chosen from its own observations). A robust round changes a few per cent
    of the tracks, so this costs a fraction of an assembly; the sums differ from a fresh one
    by rounding only. None without observations."""
    if assembled is not None and assembled[1] is not None:
        before, (LTL, extras) = assembled
        changed = np.zeros(int(parts.obs_track[-1]) + 1, dtype=bool)
        changed[parts.obs_track[before != used]] = True
        in_changed = changed[parts.obs_track]
        if np.count_nonzero(in_changed & (before | used)) <= MAX_UPDATED_FRACTION * np.count_nonzero(used):
            old, new = parts.normal_matrix(in_changed & before), parts.normal_matrix(in_changed & used)
            kept = ~changed[extras["sign_track"]]
            signs = [{key: extras[key][kept] for key in SIGN_KEYS}] + ([new[1]] if new is not None else [])
            updated = {key: np.concatenate([part[key] for part in signs]) for key in SIGN_KEYS}
            updated["constraints_per_view"] = extras["constraints_per_view"].copy()
            for sign, term in ((-1, old), (1, new)):
                if term is not None:
                    LTL = LTL + sign * term[0]
                    updated["constraints_per_view"] += sign * term[1]["constraints_per_view"]
            return LTL, updated
    normal = [part for part in parts.evaluate(used, peer=peer) if part is not None]
    return _merged_normal_matrix(normal) if normal else None


def _rigid_observations(parts: _TrackParts, keep: np.ndarray, view_mask: np.ndarray | None,
                        options: LiGTOptions) -> tuple[np.ndarray, np.ndarray]:
    """(the ``keep`` observations a solve uses: those of the largest rigid set of views
    (:func:`rigid_views`) in tracks of two or more; that set (n,) bool)."""
    used = in_tracks_of_two(parts.obs_track, keep)
    rigid = rigid_views(parts.obs_track[used], parts.obs_view[used], parts.R.shape[0], view_mask,
                        options.max_base_search_views)
    return in_tracks_of_two(parts.obs_track, used & rigid[parts.obs_view]), rigid


def _robust_rounds(parts: _TrackParts, obs_focal_px: np.ndarray, view_mask: np.ndarray | None,
                   options: LiGTOptions, peer) -> RobustLiGTResult:
    """The rounds of :func:`robust_ligt_translations` on its validated inputs."""
    obs_track = parts.obs_track
    keep = np.ones(obs_track.size, dtype=bool)
    rounds: list[dict] = []
    threshold = np.inf
    best = None  # (sigma, result, used, error, threshold) of the best solve so far
    last = None
    assembled = None  # (used, LᵀL and sign rows) of the last solve
    while True:
        # every round on the largest rigid set of what it keeps: dropping a weakly linked view's
        # few multi-view tracks would leave its distance free, and the solve would collapse
        used, rigid = _rigid_observations(parts, keep, view_mask, options)
        normal = _updated_normal_matrix(parts, assembled, used, peer)
        assembled = (used, normal)
        try:
            if normal is None:
                raise AlgorithmError("LiGT needs at least 2 constrained views, got 0")
            result = _solve_normal_matrix(*normal, rigid, options)
        except AlgorithmError:
            if last is None:
                raise
            rounds[-1]["failed"] = "the solve without the dropped observations failed; the previous one is kept"
            result, used, error = last
            break
        error = np.concatenate(parts.evaluate(used, result.centers, peer)) * obs_focal_px
        last = (result, used, error)
        finite = used & np.isfinite(error)
        if not finite.any():
            break
        sigma, final_threshold = outlier_threshold_px(error[finite], options)
        # the floor anneals: the first solve is bent by the wrong tracks, and at 1 px its errors
        # also mark the good observations of a weak link (the few tracks that tie two parts of
        # a capture together, which such a solve fits worst): dropped, they leave the link to
        # the wrong ones or cut it (castle-P19 matched sequentially lost 6-7 of 19 views)
        floor = _annealed_floor_px(len(rounds), options)
        threshold = max(final_threshold, floor)
        if best is not None and sigma > 2.0 * best[0]:
            # the solve broke down (a view lost its constraints, the eigenvector collapsed): the
            # errors of a wrecked solve would drop good observations; keep the best one
            rounds[-1]["failed"] = f"the next solve broke down (sigma {sigma:.3g} px); this one is kept"
            _, result, used, error, threshold = best
            break
        if best is None or sigma < best[0]:
            best = (sigma, result, used, error, threshold)
        if len(rounds) >= options.robust_rounds:
            break
        new_keep = error <= threshold
        dropped, readmitted = int(np.count_nonzero(used & ~new_keep)), int(np.count_nonzero(~keep & new_keep))
        rounds.append({"observations": int(used.sum()), "sigma_px": sigma, "threshold_px": threshold,
                       "dropped": dropped, "readmitted": readmitted})
        settled = dropped + readmitted <= options.min_change_fraction * max(int(used.sum()), 1)
        # not before the floor is annealed down, unless the lower floors would drop nothing either
        if settled and (threshold <= final_threshold or not np.any(used & (error > final_threshold))):
            break
        keep = new_keep
    return RobustLiGTResult(result, used, error, threshold, rounds)
