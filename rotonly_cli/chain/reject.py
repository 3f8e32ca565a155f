"""The reject stage's rounds (chain/stages.reject_stage runs them): the test of each pair's
rotation by the others (refutation), the rounds that confirm matches by their tracks
(confirmation), the outlier rounds of stages/reject with GRRM and LiGT re-solved after each,
and the snapshot a round that is undone restores."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rotonly_cli.chain.run import Run, ensure_two_views
from rotonly_cli.scene.view_graph import ViewGraph

logger = logging.getLogger(__name__)


def rejection(run: Run, solve: Callable[[str], None]) -> None:
    """Multi-view outlier rejection (the reject stage; ``solve(name)`` runs the optimize or
    translate stage on ``run`` again). First, where LiGT's first solve says a pair bends the
    rotations (:func:`_rotations_bent`), the test of each pair by the others
    (:func:`_refutation_rounds`); then, when LiGT's solve says the rotations disagree with
    the tracks (:func:`_rotations_misfit_tracks`), rounds that confirm matches by their tracks
    (:func:`_confirmation_rounds`). Then rounds of stages/reject (drop the matches inconsistent
    with the global poses) followed by GRRM and LiGT on what is left, until a round drops
    nothing (RejectOptions.max_rounds). The optimize and translate reports are those of the last
    solve, with ``time_s`` the time of every solve (first and re-solves, undone ones too) and
    ``solves`` their number; the reject report's ``time_s`` is its own checks: the stage
    times add up to the run's."""
    from rotonly_cli.scene.view_graph import view_index
    from rotonly_cli.stages.reject import reject_round
    from rotonly_cli.stages.translate import ligt_centres, views_lost, views_off

    run.options.reject.validate()
    start = time.perf_counter()
    solve_time = {k: float((run.reports.get(k) or {}).get("time_s") or 0.0) for k in ("optimize", "translate")}
    resolving = 0.0  # seconds of this stage spent in GRRM and LiGT re-solves
    solves = {"optimize": 1, "translate": 1}

    def resolve(stages: tuple[str, ...] = ("optimize", "translate")) -> None:
        """GRRM and LiGT (``stages``) again on the graph as it is now, timed into the reports'
        totals."""
        nonlocal resolving
        resolve_start = time.perf_counter()
        for key in stages:
            solve(key)
            solves[key] += 1
            solve_time[key] += float((run.reports.get(key) or {}).get("time_s") or 0.0)
        resolving += time.perf_counter() - resolve_start

    misfit = _rotations_misfit_tracks(run)  # judged on the first solve, before either changes it
    refutation = _refutation_rounds(run, resolve) if _rotations_bent(run) else None
    confirmation = _confirmation_rounds(run, resolve) if misfit else None
    rounds = []
    focal_px = run.scene.focal_px(run.graph.view_ids())
    for _ in range(run.options.reject.max_rounds):
        if run.rotations is None or run.centers is None:
            break
        before = _snapshot(run)  # what an undone round restores (reject_round changes the graph in place)
        # matches are judged under LiGT's own centres: a resected view's centre carries the error
        # of the points it was resected from (docs/tuning.md "Measurements behind the code")
        judged = ligt_centres(run.centers, run.reports.get("translate"), view_index(run.graph))
        report = reject_round(run.graph, run.scene.normalized, run.rotations, judged, focal_px,
                              run.options.reject, run.options.load.min_inliers, run.options.average.max_residual_deg)
        rounds.append(report)
        if report["num_matches"] == 0:  # a capture of pure rotations: no baseline to judge a match by
            logger.info("reject: no match on a REGULAR edge between views with a centre: nothing to judge")
            break
        logger.info("reject: %d of %d matches inconsistent with the global poses (threshold %.2f px), edges "
                    "filtered %s", report["num_dropped"], report["num_matches"], report["threshold_px"] or 0.0,
                    report["edges_filtered"] or "none")
        if report["num_dropped"] == 0 and not report["edges_filtered"]:
            break
        fewest = run.options.reject.fewest_dropped_to_resolve(report["num_edges"])
        if report["num_dropped"] < fewest and not report["edges_filtered"]:
            run.graph = before.graph  # too few to move the rotations: not worth a re-solve, not applied
            report["not_applied"] = f"fewer than {fewest} matches"
            break
        ensure_two_views(run.graph, "multi-view rejection")
        resolve()
        off_after = list(views_off(run.reports.get("translate")))
        # views resected after the solve count as lost: the round's drops cut them out of the
        # tracks' rigid set, and their rotations are the ones those drops spoiled
        lost = views_lost(before.reports["translate"], run.reports.get("translate"))
        if len(off_after) > len(views_off(before.reports["translate"])) or lost:
            # LiGT's solve on the cleaned tracks collapsed where the previous one had not, or the
            # dropped matches cut views out of the set that tracks tie together: the round is undone
            _restore(run, before)
            report["undone"] = {"views_off": off_after, "views_without_centre": lost}
            logger.info("reject: round undone, its LiGT solve %s",
                        f"put view(s) {', '.join(off_after)} off their pairs' baselines" if off_after else
                        f"left view(s) {', '.join(map(str, lost))} without a centre")
            break
    for key, seconds in solve_time.items():
        if solves[key] > 1 and isinstance(run.reports.get(key), dict) and "time_s" in run.reports[key]:
            run.reports[key] = {**run.reports[key], "time_s": seconds, "solves": solves[key]}
    run.reports["reject"] = {"rounds": rounds,  # an undone round's drops were put back
                             "num_dropped": int(sum(r["num_dropped"] for r in rounds
                                                    if "undone" not in r and "not_applied" not in r)),
                             **({"refutation": refutation} if refutation else {}),
                             **({"confirmation": confirmation} if confirmation else {}),
                             "time_s": time.perf_counter() - start - resolving}


@dataclass(frozen=True)
class _Snapshot:
    """What a re-solve of the reject stage changes, as it was before (graph copied: rounds
    change it in place)."""

    graph: ViewGraph
    rotations: np.ndarray | None
    centers: np.ndarray | None
    reports: dict  # optimize and translate; None where the run had none


def _snapshot(run: Run) -> _Snapshot:
    return _Snapshot(run.graph.copy(), run.rotations, run.centers,
                     {k: run.reports.get(k) for k in ("optimize", "translate")})


def _restore(run: Run, snapshot: _Snapshot) -> None:
    """``run`` as it was at ``snapshot``; a report it had none of is taken out again (a stage
    command's run may start without its predecessors' reports)."""
    run.graph, run.rotations, run.centers = snapshot.graph, snapshot.rotations, snapshot.centers
    for key, report in snapshot.reports.items():
        if report is None:
            run.reports.pop(key, None)
        else:
            run.reports[key] = report


def _rotations_misfit_tracks(run: Run) -> bool:
    """Whether LiGT's solve says the rotations disagree with the tracks, the cue for the
    confirmation rounds: it left views out of the set the tracks tie together, or its first
    solve (every observation in) misfits them by ``confirm_misfit_sigmas`` times the sigma of
    its last round's (the noise of the observations it kept): clean inputs stay at a few times
    (docs/tuning.md)."""
    from rotonly_cli.stages.translate import tracks_misfit, views_ligt_left_out

    options = run.options.reject
    report = run.reports.get("translate")
    if not options.confirm_max_rounds or report is None:
        return False
    return bool(views_ligt_left_out(report)) or tracks_misfit(report, options.confirm_misfit_sigmas)


def _rotations_bent(run: Run) -> bool:
    """The refutation's cue: LiGT's first solve misfits the tracks by ``confirm_misfit_sigmas``
    times its last round's sigma (the misfit half of :func:`_rotations_misfit_tracks`). Views
    left out with the rotations fitting the tracks (a weak link short of tracks) are no sign of a
    pair bending them: filtering a pair there cost views and accuracy."""
    from rotonly_cli.stages.translate import tracks_misfit

    options = run.options.reject
    report = run.reports.get("translate")
    return bool(options.refute_max_edges) and report is not None and \
        tracks_misfit(report, options.confirm_misfit_sigmas)


def _leaves_new_bridges(graph, edge: int, bridges: set[int]) -> bool:
    """Whether filtering ``edge`` would leave an active edge on no cycle that is on one now."""
    from rotonly_cli.scene.view_graph import active_bridges

    status = graph.edges[edge].status
    graph.edges[edge].status = "filtered"
    try:
        return bool(set(active_bridges(graph)) - bridges)
    finally:
        graph.edges[edge].status = status


def _refutation_rounds(run: Run, resolve) -> dict:
    """Where LiGT's first solve misfits the tracks (:func:`_rotations_bent`), pairs that the
    other pairs refute are filtered (stages/reject.refuted_edges, geometry/refutation): a pair whose
    matches are consistently wrong (repeated structure that fits its own epipolar geometry)
    bends GRRM's rotations until its own matches fit them, and where it is weakly tied, no
    residual under the bent rotations shows it. Left out, its matches misfit the rotation the
    others imply: the most refuted pair beyond ``refute_max_ratio`` is filtered and GRRM and
    LiGT re-solved, at most ``refute_max_edges`` times. A filtered pair is put back, and the
    test ends, when LiGT then leaves out a view it tied in (the pair was a link the tracks
    needed) or misfits the tracks by more than ``refute_max_misfit_growth`` times the misfit
    before. Returns the report."""
    from rotonly_cli.scene.view_graph import active_bridges
    from rotonly_cli.stages.optimize import grrm_inputs
    from rotonly_cli.stages.reject import REFUTE_REASON, refuted_edges
    from rotonly_cli.stages.translate import first_solve_sigma_px, views_lost

    options = run.options.reject
    rounds = []
    for _ in range(options.refute_max_edges):
        if run.rotations is None:
            break
        inputs = grrm_inputs(run.graph, run.scene.normalized, run.rotations)
        candidates = [entry for entry in refuted_edges(run.graph, inputs, run.rotations)
                      if entry["fit_ratio"] > options.refute_max_ratio]
        # the others refute a pair only where they stay redundant: a pair whose loss would
        # leave other pairs on no cycle had one path to disagree with, and nothing would check
        # those pairs afterwards. Then the test ends: the pairs below
        # the most refuted one may be the ones it bent (a simulated pair turned 1.5 deg: 31x,
        # its neighbours up to 11x)
        if not candidates or _leaves_new_bridges(run.graph, candidates[0]["edge_index"],
                                                 set(active_bridges(run.graph))):
            break
        worst = candidates[0]
        before = _snapshot(run)
        misfit_before = first_solve_sigma_px(before.reports["translate"])
        run.graph.edges[worst["edge_index"]].filter(f"{REFUTE_REASON}: its matches fit the others' rotation "
                                                    f"{worst['fit_ratio']:.3g}x worse than its own")
        ensure_two_views(run.graph, "leave-one-out refutation")
        resolve()
        misfit = first_solve_sigma_px(run.reports.get("translate"))
        lost = views_lost(before.reports["translate"], run.reports.get("translate"))
        kept = not lost and not misfit > options.refute_max_misfit_growth * misfit_before  # nan: no test
        entry = {"edge": worst["edge"], "fit_ratio": worst["fit_ratio"],
                 "rotation_change_deg": worst["rotation_change_deg"], "first_solve_sigma_px": [misfit_before, misfit],
                 "views_left_out": lost, "kept": kept}
        rounds.append(entry)
        logger.info("reject: pair %d-%d refuted by the others (its matches fit their rotation %.3g x worse than its "
                    "own, %.3g deg away): filtered; LiGT's first solve %.3g -> %.3g px off the tracks%s: %s",
                    *worst["edge"], worst["fit_ratio"], worst["rotation_change_deg"], misfit_before, misfit,
                    f", view(s) {', '.join(map(str, lost))} left out" if lost else "",
                    "kept" if kept else "undone")
        if not kept:
            _restore(run, before)
            break
    return {"max_ratio": options.refute_max_ratio, "rounds": rounds}


def _confirmation_rounds(run: Run, resolve) -> dict:
    """Where LiGT's solve says the rotations disagree with the tracks
    (:func:`_rotations_misfit_tracks`), GRRM's objective, which takes every match of a pair,
    may have been bent by wrong matches that fit their own pair's epipolar geometry (repeated
    structure a few pixels off the right line, no third view to refute them; docs/tuning.md
    "Confirmation by tracks").

    Each round triangulates the tracks under the current poses (every view with a centre,
    resected ones too), keeps on every edge only the matches a track of ``confirm_min_views``
    or more views holds (stages/reject.confirmed_matches, chosen afresh from the edges' matches
    before the rounds), and re-solves GRRM and LiGT (``resolve``), until the confirmed matches
    stop changing or ``confirm_max_rounds``. Skipped when fewer than ``confirm_min_fraction``
    of the matches are confirmed.

    The test is LiGT on every match under the new rotations: kept when its first solve
    misfits the tracks by at most ``confirm_misfit_ratio`` of the sigma before, it ties every
    view in, no pair becomes an outlier of the averaging and no view comes off its pairs'
    baselines. The rotations then start the rejection rounds, which judge every match under
    the new poses: the unconfirmed matches are not dropped for being unconfirmed. Otherwise
    the rounds are undone. Returns the report."""
    from rotonly_cli.scene.view_graph import edge_residuals_deg, view_index
    from rotonly_cli.stages.reject import confirm_round, confirmed_matches
    from rotonly_cli.stages.translate import first_solve_sigma_px, views_ligt_left_out, views_off
    from rotonly_cli.stages.triangulate import posed_edges, triangulated_tracks

    options = run.options.reject
    saved = _snapshot(run)
    original = saved.graph  # the edges' matches before the rounds; every round copies it
    index = view_index(original)

    def residuals() -> np.ndarray:  # every active edge against the run's rotations now
        return edge_residuals_deg([original.edges[k] for k in original.active_edges()],
                                  {v: run.rotations[row] for v, row in index.items()})

    left_before = sorted(views_ligt_left_out(saved.reports["translate"]))
    residual_before, misfit_before = residuals(), first_solve_sigma_px(saved.reports["translate"])
    rounds, previous, result = [], None, {}
    for _ in range(options.confirm_max_rounds):
        edges = posed_edges(original, run.rotations, run.centers)[1]
        tracks = triangulated_tracks(run.graph, run.scene, run.rotations, run.centers, run.options.triangulate,
                                     run.tracks, run.options.translate).kept
        confirmed = confirmed_matches(original, tracks, edges, options.confirm_min_views)
        signature = [(k, keep.tobytes()) for k, keep in zip(edges, confirmed)]
        if signature == previous:
            break
        previous = signature
        graph, report = confirm_round(original, confirmed, edges)
        if report["num_dropped"] > (1.0 - options.confirm_min_fraction) * report["num_matches"]:
            # most matches unconfirmed: tracks of three views are too few for a consistency
            # test, and GRRM on the rest would be a thin subsample
            result = {"too_few_confirmed": report}
            break
        run.graph = graph
        ensure_two_views(run.graph, "multi-view confirmation")
        resolve()
        report["views_left_out"] = sorted(views_ligt_left_out(run.reports.get("translate")))
        rounds.append(report)
        logger.info("reject: %d of %d matches not in a track of %d or more views (%d edges kept whole); after GRRM "
                    "and LiGT on the rest, LiGT leaves %s out", report["num_dropped"], report["num_matches"],
                    options.confirm_min_views, report["edges_kept_whole"],
                    f"view(s) {', '.join(map(str, report['views_left_out']))}" if report["views_left_out"] else
                    "no view")
    result = {"views_left_out_before": left_before, "rounds": rounds, **result}
    if not rounds:
        logger.info("reject: %d of %d matches lie in tracks of %d or more views: too few to confirm matches by",
                    result["too_few_confirmed"]["num_matches"] - result["too_few_confirmed"]["num_dropped"],
                    result["too_few_confirmed"]["num_matches"], options.confirm_min_views)
        return result
    # the test: LiGT on every match's tracks (the graph before the rounds) under the new
    # rotations. Where wrong matches had bent the rotations, the tracks now agree with them
    # and LiGT ties every view in; where views were left out for want of tracks (a weak
    # link), some stay out, and the rounds are undone
    run.graph = original.copy()
    resolve(("translate",))
    left_all = sorted(views_ligt_left_out(run.reports.get("translate")))
    # ... and the new rotations may not put a pair beyond the averaging's outlier residual
    # (a leaf can turn far) nor a view off its pairs' baselines (LiGT shrinking the centres fits every track)
    outlier = run.options.average.max_residual_deg
    new_outliers = int(np.sum((residuals() > outlier) & ~(residual_before > outlier)))
    off = sorted(set(views_off(run.reports.get("translate"))) - set(views_off(saved.reports["translate"])))
    misfit = first_solve_sigma_px(run.reports.get("translate"))
    result.update(views_left_out_all_matches=left_all, new_outlier_edges=new_outliers, new_views_off=off,
                  first_solve_sigma_px=[misfit_before, misfit])
    failed = [reason for reason, failing in (
        (f"LiGT's first solve misfits the tracks by {misfit:.3g} px (before {misfit_before:.3g})",
         not misfit <= options.confirm_misfit_ratio * misfit_before),
        (f"LiGT leaves view(s) {', '.join(map(str, left_all))} out (for want of tracks, not for bent rotations)",
         bool(left_all)),
        (f"{new_outliers} pair(s) become outliers of the averaging", bool(new_outliers)),
        (f"view(s) {', '.join(off)} come off their pairs' baselines", bool(off))) if failing]
    if not failed:
        logger.info("reject: under the rotations of the confirmed matches LiGT's first solve on every match "
                    "misfits the tracks by %.3g px (before %.3g) and ties every view in: kept", misfit, misfit_before)
        return result
    _restore(run, saved)
    logger.info("reject: confirmation undone: under the rotations of the confirmed matches %s", "; ".join(failed))
    return {**result, "undone": True}
