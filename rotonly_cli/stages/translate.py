"""Stage `translate`: camera centres by LiGT from the global rotations and the tracks of the
active REGULAR edges (PURE_ROTATION edges carry no translation information, paper
§"Scene Identification"). Views LiGT cannot constrain (without a constraint, or outside the largest
rigid set, geometry.ligt.rigid, whose distance to the others no track through three or more
views ties down) are resected from the points of the others, their rotations known
(geometry.resection, algorithms.md §1.5). A view still without a centre whose pair with a
positioned view is a pure rotation (PURE_ROTATION: PR/B/I, its translation unobservable) is
given that view's centre, and a capture of pure rotations only (a panorama) one shared centre
(algorithms.md §1.6). The rest get NaN centres (not registered)."""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.identification import SceneKind
from rotonly_cli.geometry.ligt import (
    LiGTOptions,
    baseline_disagreement_deg,
    robust_ligt_translations,
    views_off_their_baselines,
)
from rotonly_cli.geometry.resection import resect_left_out_views
from rotonly_cli.scene.tracks import TrackCache, graph_tracks, robust_weights
from rotonly_cli.scene.view_graph import ViewGraph, largest_component_of, regular_edges, view_index
from rotonly_cli.stages import listed, map_graph_edges

logger = logging.getLogger(__name__)

#: the robust rounds take a helper process (runtime.parallel.helper_class) from this many
#: observations on: below, a fork gains nothing worth it (docs/tuning.md "Measurements behind
#: the code")
LIGT_HELPER_MIN_OBSERVATIONS = 50_000
#: matches per --cluster task of the tracks' robust match weights (as TRRM's, stages/refine.py)
WEIGH_TASK_MATCHES = 1 << 19


def match_weigher(graph: ViewGraph, normalized: dict[int, np.ndarray], jobs: int):
    """scene.tracks.inlier_matches' ``weigh``: the robust weights of the matches of some edges
    computed over ``jobs`` forked processes (or the --cluster session), chunk by chunk, as the
    per-edge stages are (the 1000-view recipe: 20 M matches, 6-7 s in one process)."""
    def weigh(edges: list[int], R_ij: np.ndarray) -> np.ndarray:
        return map_graph_edges("tracks", robust_weights, graph, normalized, edges, R_ij, jobs,
                               WEIGH_TASK_MATCHES)[0].weights

    return weigh


def translate_graph(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                    options: LiGTOptions | None = None, track_cache: TrackCache | None = None,
                    focal_px: np.ndarray | None = None, jobs: int = 1) -> tuple[np.ndarray, dict]:
    """(centres (n, 3), NaN where unknown; report). ``track_cache``: the run's, shared
    with triangulate (scene/tracks). ``focal_px`` (n,): each view's focal length, the unit of
    the outlier threshold of the robust rounds (default 1000 px). ``jobs``: processes of the
    robust rounds (robust_ligt_translations; the numbers do not depend on it)."""
    start = time.perf_counter()
    index = view_index(graph)
    registered = np.all(np.isfinite(R_cam_from_world.reshape(len(index), -1)), axis=1)
    edges = [k for k in regular_edges(graph) if registered[index[graph.edges[k].i]]
             and registered[index[graph.edges[k].j]]]
    if not edges:
        return _pure_rotation_capture(graph, index, registered, start)
    R = np.where(registered[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, normalized, edges, R, cache=track_cache,
                                  weigh=match_weigher(graph, normalized, jobs))
    focal = np.full(len(index), 1000.0) if focal_px is None else np.where(np.isfinite(focal_px), focal_px, 1000.0)
    from rotonly_cli.runtime.parallel import helper_class

    # half of every round's LᵀL and triangulation in a forked child where that is safe and pays
    peer_class = helper_class(tracks.num_observations, jobs, LIGT_HELPER_MIN_OBSERVATIONS)
    options = options or LiGTOptions()

    def solve(ligt_options: LiGTOptions):
        robust = robust_ligt_translations(R, tracks.track_id, tracks.view, obs_xy, focal[tracks.view],
                                          view_mask=registered, options=ligt_options, peer_class=peer_class)
        centers = np.where(robust.result.has_translation[:, None], robust.result.centers, np.nan)
        return robust, centers, baseline_report(graph, edges, index, R, centers, ligt_options)

    robust, centers, baselines = solve(options)
    annealing = None
    if baselines["views_off"] and options.outlier_threshold_start_px is not None:
        # the annealed rounds kept a weak link that the 1 px rounds would have cut, and its
        # tracks put views off their own pairs' directions: the rounds without annealing are
        # tried, and kept if fewer views are off
        plain_robust, plain_centers, plain_baselines = solve(replace(options, outlier_threshold_start_px=None))
        taken = len(plain_baselines["views_off"]) < len(baselines["views_off"])
        annealing = {"views_off": baselines["views_off"], "without_views_off": plain_baselines["views_off"],
                     "kept": "without annealing" if taken else "annealed"}
        if taken:
            robust, centers, baselines = plain_robust, plain_centers, plain_baselines
    result = robust.result
    ids = graph.view_ids()
    resected = []
    left_out = np.flatnonzero(registered & ~np.all(np.isfinite(centers), axis=1))
    if options.resection is not None and left_out.size:
        # the robust rounds cut a weak link (wrong tracks bent their first solve): the views
        # beyond it, rotations known, are resected from the points of the others
        threshold_px = max(robust.threshold_px if np.isfinite(robust.threshold_px) else 0.0,
                           options.resection.min_threshold_px)
        centers, resected = resect_left_out_views(R, centers, tracks.track_id, tracks.view, obs_xy,
                                                  threshold_px / focal, left_out, options.resection)
        if resected:
            baselines = baseline_report(graph, edges, index, R, centers, options)
            # a resected centre its own pairs' directions disagree with is no position
            for entry in resected:
                entry["view_id"] = ids[entry.pop("view")]
                entry["kept"] = str(entry["view_id"]) not in baselines["views_off"]
                if not entry["kept"]:
                    centers[index[entry["view_id"]]] = np.nan
            if not all(entry["kept"] for entry in resected):
                baselines = baseline_report(graph, edges, index, R, centers, options)
    centers, shared = share_pure_rotation_centres(graph, index, centers, registered)
    has_centre = np.all(np.isfinite(centers), axis=1)
    without = [ids[r] for r in np.flatnonzero(registered & ~has_centre)]
    report = {"num_edges": len(edges), "num_tracks": tracks.num_tracks, "num_observations": tracks.num_observations,
              "num_inconsistent_tracks": tracks.num_inconsistent,
              "num_views_with_centre": int(has_centre.sum()),
              "views_without_centre": without, "smallest_eigenvalues": result.smallest_eigenvalues.tolist(),
              "sign_votes": list(result.sign_votes), "robust_rounds": robust.rounds,
              "num_observations_used": int(robust.keep.sum()),
              "num_observations_dropped": int(tracks.num_observations - robust.keep.sum()),
              "outlier_threshold_px": robust.threshold_px, "baselines": baselines,
              **({"annealing_checked": annealing} if annealing else {}),
              **({"resected": resected} if resected else {}),
              **({"shared_centres": shared} if shared else {}),
              "processes": 1 if peer_class is None else 2,
              "time_s": time.perf_counter() - start}
    for number, round_ in enumerate(robust.rounds, 1):
        logger.debug("translate round %d: %d observations, sigma %.3f px, threshold %.2f px, %d dropped, "
                     "%d re-admitted", number, round_["observations"], round_["sigma_px"], round_["threshold_px"],
                     round_["dropped"], round_["readmitted"])
    _log_shared(shared)
    kept = [str(entry["view_id"]) for entry in resected if entry["kept"]]
    if kept:
        logger.info("translate: view(s) %s resected from the points of the others (their rotations known): LiGT's "
                    "outlier rounds had left no track through three or more views tying them in", listed(kept))
    shown = listed(map(str, without))
    logger.info("translate (LiGT): %d tracks, %d REGULAR edges, %d views with a centre%s; %d of %d "
                "observations kept", tracks.num_tracks, len(edges), report["num_views_with_centre"],
                f", {len(without)} without (views {shown}: outside the largest set of views whose distances "
                f"tracks of three or more views tie together, and not resected; not registered)" if without else "",
                report["num_observations_used"], tracks.num_observations)
    return centers, report


def _pure_rotation_edges(graph: ViewGraph, index: dict[int, int], registered: np.ndarray) -> list:
    """The active PURE_ROTATION edges between registered views."""
    return [graph.edges[k] for k in graph.active_edges()
            if graph.edges[k].scene_kind == SceneKind.PURE_ROTATION.value
            and registered[index[graph.edges[k].i]] and registered[index[graph.edges[k].j]]]


def share_pure_rotation_centres(graph: ViewGraph, index: dict[int, int], centers: np.ndarray,
                                registered: np.ndarray) -> tuple[np.ndarray, list[dict]]:
    """(centres, entries): every registered view without a centre that an active
    PURE_ROTATION edge joins to a view with one takes that view's centre, breadth first (the
    fewest pure-rotation pairs away; among a view's neighbours the pair with the most
    matches). A pure rotation (PR) has one centre for both views; under B/I (points on the
    baseline or at infinity) the translation is unobservable and the shared centre is the
    estimate the matches cannot tell from the truth (paper §"Scene Identification",
    Corollary 1 case 1). Entries: view_id, from_view_id (the view whose centre it took)."""
    centers = np.array(centers, dtype=float)
    has_centre = np.all(np.isfinite(centers), axis=1)
    # strongest pairs first, so that a view reached in the same sweep from several takes the best
    pure = sorted(_pure_rotation_edges(graph, index, registered), key=lambda edge: -edge.num_inliers)
    ids = graph.view_ids()
    shared = []
    frontier = has_centre.copy()
    while True:
        reached = {}
        for edge in pure:
            a, b = index[edge.i], index[edge.j]
            for source, target in ((a, b), (b, a)):
                if frontier[source] and not has_centre[target] and target not in reached:
                    reached[target] = source
        if not reached:
            return centers, shared
        frontier = np.zeros_like(has_centre)
        for target, source in sorted(reached.items()):
            centers[target] = centers[source]
            has_centre[target] = frontier[target] = True
            shared.append({"view_id": ids[target], "from_view_id": ids[source]})


def _pure_rotation_capture(graph: ViewGraph, index: dict[int, int], registered: np.ndarray, start: float):
    """translate_graph without a REGULAR edge: every pair a pure rotation (a panorama from a
    tripod, or a distant scene). The best-connected view of the largest set joined by
    PURE_ROTATION edges is put at the origin and the views it rotates about share its centre;
    nothing fixes a scale (no points can be triangulated)."""
    pairs = [(edge.i, edge.j) for edge in _pure_rotation_edges(graph, index, registered)]
    largest = largest_component_of(graph.view_ids(), pairs)
    if not largest:
        raise AlgorithmError("translation: no REGULAR or PURE_ROTATION edge between registered views")
    degree = {v: 0 for v in largest}
    for i, j in pairs:
        if i in degree:
            degree[i] += 1
            degree[j] += 1
    seed = index[max(largest, key=lambda v: degree[v])]  # the first of the best connected
    centers = np.full((len(index), 3), np.nan)
    centers[seed] = 0.0
    centers, shared = share_pure_rotation_centres(graph, index, centers, registered)
    has_centre = np.all(np.isfinite(centers), axis=1)
    ids = graph.view_ids()
    without = [ids[r] for r in np.flatnonzero(registered & ~has_centre)]
    report = {"num_edges": 0, "num_tracks": 0, "num_observations": 0, "num_inconsistent_tracks": 0,
              "num_views_with_centre": int(has_centre.sum()), "views_without_centre": without,
              "pure_rotation_capture": {"origin_view_id": ids[seed]}, "shared_centres": shared,
              "time_s": time.perf_counter() - start}
    logger.info("translate: no REGULAR edge, every pair a pure rotation: %d view(s) share the centre of view %s",
                len(shared) + 1, ids[seed])
    _log_shared(shared)
    return centers, report


def _log_shared(shared: list[dict]) -> None:
    if shared:
        views = sorted(entry["view_id"] for entry in shared)
        logger.info("translate: view(s) %s given the centre of a view they are a pure rotation from (PURE_ROTATION "
                    "pairs: the translation is unobservable)", listed(map(str, views)))


def baseline_report(graph: ViewGraph, edges: list[int], index: dict[int, int], R_cam_from_world: np.ndarray,
                    centers: np.ndarray, options: LiGTOptions) -> dict:
    """The check of the centres against the edges' own translation directions
    (ligt.baseline_disagreement_deg): the spread of the angles over the edges and the views
    whose median exceeds ``options.max_baseline_disagreement_deg`` (by view id, with their
    medians). LiGT's least-squares null vector can put a weakly constrained view far off
    while the other centres shrink around one point (a collapse no reprojection error shows:
    the points triangulate from the collapsed cameras all the same)."""
    ends = np.array([[index[graph.edges[k].i], index[graph.edges[k].j]] for k in edges], dtype=np.int64)
    t_dirs = np.array([graph.edges[k].t_dir for k in edges], dtype=float)
    angles = baseline_disagreement_deg(R_cam_from_world, centers, ends, t_dirs)
    medians, off = views_off_their_baselines(angles, ends, len(index), options.max_baseline_disagreement_deg)
    ids = graph.view_ids()
    finite = angles[np.isfinite(angles)]
    return {"num_edges": int(finite.size),
            "angle_deg": ({"median": float(np.median(finite)), "p90": float(np.percentile(finite, 90)),
                           "max": float(finite.max())} if finite.size else None),
            "threshold_deg": options.max_baseline_disagreement_deg,
            "views_off": {str(ids[v]): float(medians[v]) for v in off.tolist()}}


def views_off(report: dict | None) -> dict[str, float]:
    """The views a translate report's baseline check found off ({view id: median angle});
    empty for no report or one without the check."""
    return ((report or {}).get("baselines") or {}).get("views_off") or {}


def _round_sigma_px(report: dict | None, which: int) -> float:
    """The robust sigma (px) of a translate report's robust round ``which`` (nan without any)."""
    rounds = (report or {}).get("robust_rounds") or []
    return float(rounds[which]["sigma_px"]) if rounds else float("nan")


def first_solve_sigma_px(report: dict | None) -> float:
    """The robust sigma (px) of the reprojection errors of LiGT's first solve, every
    observation of the tracks in (before any robust round drops one): how far the rotations
    are from what the tracks say (nan without robust rounds)."""
    return _round_sigma_px(report, 0)


def last_round_sigma_px(report: dict | None) -> float:
    """The robust sigma (px) of the reprojection errors of LiGT's last robust round: the noise
    of the observations it kept (nan without robust rounds)."""
    return _round_sigma_px(report, -1)


def tracks_misfit(report: dict | None, misfit_sigmas: float) -> bool:
    """Whether LiGT's first solve misfits the tracks: its sigma beyond ``misfit_sigmas``
    times its last robust round's (False without robust rounds)."""
    return first_solve_sigma_px(report) > misfit_sigmas * last_round_sigma_px(report)


def views_without_centre(report: dict | None) -> set[int]:
    """The registered views a translate report left without a centre (empty for no report)."""
    return set((report or {}).get("views_without_centre") or [])


def views_not_ligt(report: dict | None) -> set[int]:
    """The views a translate report positioned other than by LiGT: resected (and kept) or
    given the centre of a view they are a pure rotation from."""
    report = report or {}
    return ({entry["view_id"] for entry in report.get("resected") or [] if entry["kept"]}
            | {entry["view_id"] for entry in report.get("shared_centres") or []})


def views_ligt_left_out(report: dict | None) -> set[int]:
    """The registered views a translate report's LiGT solve left without a centre, whether
    positioned afterwards or not (empty for no report)."""
    report = report or {}
    return views_without_centre(report) | {entry["view_id"] for entry in (report.get("resected") or [])
                                           + (report.get("shared_centres") or [])}


def views_lost(before: dict | None, after: dict | None) -> list[int]:
    """The views the LiGT solve of translate report ``after`` left without a centre (positioned
    afterwards or not) that the solve of ``before`` had placed on their pairs' baselines: a
    view it left out or put off them (a collapsed centre) had no position to lose."""
    placed_not = views_ligt_left_out(before) | {int(view_id) for view_id in views_off(before)}
    return sorted(views_ligt_left_out(after) - placed_not)


def ligt_centres(centers: np.ndarray, report: dict | None, index: dict[int, int]) -> np.ndarray:
    """``centers`` with the views the translate ``report`` positioned other than by LiGT set
    to NaN: LiGT's own centres (``index``: view id -> row)."""
    others = [index[view_id] for view_id in views_not_ligt(report)]
    if not others:
        return centers
    own = np.array(centers, dtype=float)
    own[others] = np.nan
    return own


def unregistered_warning(num_views: int, unregistered: list[int], report: dict | None,
                         without_camera: frozenset[int] | set[int] = frozenset()) -> str | None:
    """The run summary's warning when views are left out of the outputs (``unregistered``, by
    view id; ``report``: the translate report): those the input gives no camera
    (``without_camera``: an OpenMVG view whose intrinsic is undefined, under ``--intrinsics
    fixed``), those with rotations but no centre (outside the rigid set: no track through
    three or more views ties them to the rest, as on a sequentially matched capture with
    little overlap, and too few points to resect them from) and those the view graph's checks
    cut off. None when every view is in."""
    if not unregistered:
        return None
    without = views_without_centre(report)
    uncalibrated = [str(v) for v in unregistered if v in without_camera]
    apart = [str(v) for v in unregistered if v not in without and v not in without_camera]
    no_position = [str(v) for v in unregistered if v in without and v not in without_camera]
    parts = []
    if uncalibrated:
        parts.append(f"view(s) {listed(uncalibrated)} have no camera in the input (an undefined intrinsic: no EXIF "
                     f"focal when the images were listed), which --intrinsics fixed cannot use (auto guesses and "
                     f"calibrates one)")
    if apart:
        parts.append(f"view(s) {listed(apart)} have no pair left that ties them to the largest part of the view graph "
                     f"(reports/view_graph.json: each dropped edge's reason)")
    if no_position:
        parts.append(f"view(s) {listed(no_position)} have a rotation but no position: of the tracks LiGT's outlier "
                     f"rounds kept, none through three or more views ties them to the rest, and too few of their "
                     f"points agree with a centre resected from the others (reports/translate.json: "
                     f"views_without_centre)")
    tie = "; images overlapping them and the rest would tie them in" if apart or no_position else ""
    return f"{len(unregistered)} of {num_views} views are not in the outputs: {'; '.join(parts)}{tie}"


def pure_rotation_warning(report: dict | None) -> str | None:
    """The run summary's warning for a capture whose every pair is a pure rotation (a
    panorama): the views share one centre, so the outputs hold no points."""
    capture = (report or {}).get("pure_rotation_capture")
    if not capture:
        return None
    return (f"every pair is a pure rotation (PR/B/I: a panorama, or a scene too distant for the baselines): "
            f"the {report['num_views_with_centre']} views share the centre of view {capture['origin_view_id']}, "
            f"their rotations are the result, and no point can be triangulated (reports/translate.json)")


def baseline_warning(report: dict | None) -> str | None:
    """The run summary's warning when the translate report's baseline check found views off."""
    off = views_off(report)
    if not off:
        return None
    shown = listed(f"{v} ({angle:.0f} deg)" for v, angle in off.items())
    return (f"positions may have collapsed: the centre(s) of {len(off)} view(s) disagree with their pairs' own "
            f"translation directions by more than {report['baselines']['threshold_deg']:g} deg (median over their "
            f"edges): view {shown}; LiGT may have shrunk the other centres around "
            f"one point (reports/translate.json)")
