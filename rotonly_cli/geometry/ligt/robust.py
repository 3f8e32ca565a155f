"""Robust LiGT: reprojection errors of the observations under the solved centres, and rounds
that drop the observations beyond a noise-scaled threshold and solve again (algorithms.md §1.3,
docs/tuning.md "Robust LiGT"), updating the normal matrix by the observations that changed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.ligt.linear import (
    SIGN_KEYS,
    LiGTResult,
    merged_normal_matrix,
    solve_normal_matrix,
    validated,
    view_masked_normal_matrix,
)
from rotonly_cli.geometry.ligt.rigid import rigid_views
from rotonly_cli.geometry.tracks import (
    EVALUATION_PARTS,
    compact_track_ids,
    even_ranges,
    in_tracks_of_two,
    track_starts,
)
from rotonly_cli.options import LiGTOptions


@dataclass
class RobustLiGTResult:
    result: LiGTResult  # the last solve
    keep: np.ndarray  # (N_obs,) bool: observations of that solve
    error_px: np.ndarray  # (N_obs,) reprojection error at the last solve (inf: no point / no centre)
    threshold_px: float  # outlier threshold of the last round (inf without rounds)
    rounds: list[dict]  # per round: observations used, sigma, threshold, dropped, re-admitted


#: Gauss-Newton steps of the points of :func:`observation_errors`: their errors decide drops at
#: a pixel or more, and with 2 (of the final triangulation's 5) every drop on the measured inputs
#: is the same (the written models are byte-identical) for a quarter of the call's time
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
        return view_masked_normal_matrix(self.R, self.obs_track[a:b][used], self.obs_view[a:b][used],
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
    R, obs_track, obs_view, obs_xy = validated(R_cam_from_world, obs_track, obs_view, obs_xy)
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
    return merged_normal_matrix(normal) if normal else None


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
            result = solve_normal_matrix(*normal, rigid, options)
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
        # the wrong ones or cut it
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
