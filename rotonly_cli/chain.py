"""The chain in memory: the Run every stage shares, the stages, and the passes that calibrate
the intrinsics (--intrinsics, algorithms.md §8).

load (INPUT -> view graph, re-estimated relative poses, min-inlier filter)
-> identify (scene kinds; ROTATION_SINGULAR filtered) -> refine (TRRM, batched)
-> average (L1-IRLS, gross-outlier filter) -> optimize (GRRM) -> translate (robust LiGT)
-> reject (multi-view outlier rejection, then GRRM + LiGT again) -> triangulate (+ colours).
pipeline.py runs it into a workspace (files, OUT handling, stage subcommands).
"""

from __future__ import annotations

import copy
import functools
import logging
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.options import RunOptions
from rotonly_cli.reject_rounds import (  # noqa: F401 (re-exported: the tests reach them through the chain)
    _confirmation_rounds,
    _ensure_two_views,
    _leaves_new_bridges,
    _refutation_rounds,
    _restore,
    _rotations_bent,
    _rotations_misfit_tracks,
    _snapshot,
)
from rotonly_cli.scene.tracks import TrackCache
from rotonly_cli.scene.types import SfMScene, Structure
from rotonly_cli.scene.view_graph import ViewGraph
from rotonly_cli.stages.load import NOT_MEASURED

if TYPE_CHECKING:
    from rotonly_cli.calibration import Calibration

logger = logging.getLogger(__name__)

STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


@dataclass
class Run:
    """Everything the stages produce, in memory."""

    input_path: str
    input_kind: InputKind
    scene: SfMScene
    graph: ViewGraph
    options: RunOptions
    rotations: np.ndarray | None = None  # (n, 3, 3) sorted-view-id rows, NaN = unregistered
    centers: np.ndarray | None = None
    structure: Structure | None = None
    reports: dict = field(default_factory=dict)
    #: keypoint colours being decoded on a thread since loading (stages.triangulate)
    keypoint_rgb: Future | None = None
    #: tracks built by translate and reused by triangulate (scene/tracks)
    tracks: TrackCache = field(default_factory=TrackCache)
    #: the intrinsics as read, before any stage changed them (report.html)
    input_intrinsics: dict = field(default_factory=dict)
    #: the camera calibration of this run (calibration.Calibration)
    calibration: Calibration | None = None
    components: list = field(default_factory=list)  #: the graph's other parts (components.Component)


# ============================================================================ stages in memory



def load_stage(input_path: str | Path, options: RunOptions, scratch: Path | None = None) -> Run:
    """``scratch``: where a database's private copy is made (the run's staging folder)."""
    from rotonly_cli.stages.load import input_files, read_input

    start = time.perf_counter()
    scene, kind = read_input(input_path, options.matches_dir, options.matches_file, scratch)
    sources = input_files(input_path, kind, scene, options.matches_dir, options.matches_file)
    return load_scene(scene, kind, str(input_path), options, time.perf_counter() - start, sources)


def load_scene(scene: SfMScene, kind: InputKind, input_label: str, options: RunOptions, read_time: float = 0.0,
               sources: dict | None = None) -> Run:
    """The load stage on a scene already read (``input_label``: its path, or what it was made
    from; ``sources``: what it was read from, stages.load.input_files, for reports/load.json):
    the focal lengths the input marks as guesses calibrated (--intrinsics), the view graph built."""
    from rotonly_cli.calibration import guess_missing_cameras, start_calibration
    from rotonly_cli.options import Intrinsics
    from rotonly_cli.stages.load import measure_noise, without_unprojectable_keypoints

    started = time.perf_counter()
    scene, guessed_views = guess_missing_cameras(scene, options.intrinsics.mode, kind == InputKind.OPENMVG)
    with_camera = [v for v, view in scene.views.items() if view.intrinsics_id in scene.intrinsics]
    if len(with_camera) < min(2, len(scene.views)):  # views without a camera under --intrinsics fixed
        raise InputError(f"{len(scene.views) - len(with_camera)} of {len(scene.views)} views have no camera (an "
                         f"undefined intrinsic: no EXIF focal when the images were listed), which --intrinsics fixed "
                         f"cannot use (auto guesses and calibrates one)", path=input_label, field="intrinsics")
    scene, unprojectable = without_unprojectable_keypoints(scene)
    read_time += time.perf_counter() - started
    started = time.perf_counter()
    calibration = start_calibration(scene, options.intrinsics, jobs=options.jobs)
    calibration.time_s += time.perf_counter() - started
    noise, noise_time = NOT_MEASURED, 0.0  # the load stage's own noise measurement, if made early
    if options.intrinsics.mode == Intrinsics.AUTO and not calibration.calibrate:
        started = time.perf_counter()
        noise = measure_noise(scene, _load_options(options))
        noise_time = time.perf_counter() - started
        started = time.perf_counter()
        if _probe_for_suspects(input_label, kind, calibration, options, noise):
            # other intrinsics: the load stage measures again; this measurement served the calibration
            noise = NOT_MEASURED
            calibration.time_s += noise_time
            noise_time = 0.0
        calibration.time_s += time.perf_counter() - started
    run = _build_graph(input_label, kind, calibration.scene, options, noise_sigma=noise)
    run.reports["load"]["time_s"] += noise_time
    run.calibration = calibration
    run.input_intrinsics = copy.deepcopy(scene.intrinsics)
    run.reports["load"].update(read_time_s=read_time, input=input_label, input_kind=kind,
                               **(sources or {"input_files": []}), **unprojectable)
    if guessed_views:
        run.reports["load"]["views_given_a_guessed_camera"] = guessed_views
    return run


def _probe_for_suspects(input_label: str, kind: InputKind, calibration: Calibration, options: RunOptions,
                        noise_sigma) -> bool:
    """auto, no camera marked as a guess, the matches' noise under the essential-matrix model
    (the load stage's measurement) above ``probe_noise_px``: an estimation pass
    (ESTIMATION_LOAD, ESTIMATION_STAGES) whose reprojection errors tell whether some camera's
    intrinsics are wrong, before the full load stage and chain run with them (with a wrong
    EXIF focal that pass costs a fifth of them: docs/tuning.md "Intrinsics"). True if some
    camera joined the calibration. Calibrated inputs (noise 0.13-0.25 px on Strecha) never
    probe."""
    if not isinstance(noise_sigma, float) or noise_sigma <= options.intrinsics.probe_noise_px:
        return False
    logger.info("intrinsics: the matches fit essential matrices at sigma %.2f px (> %.2f px): a quick estimation "
                "pass checks the cameras first", noise_sigma, options.intrinsics.probe_noise_px)
    try:
        probe = _build_graph(input_label, kind, calibration.scene, options, estimation=True, noise_sigma=noise_sigma)
        probe = _rerun(probe, calibration.scene, probe, estimation=True)
    except AlgorithmError as exc:  # the full chain decides, as without the probe
        logger.info("intrinsics: the quick estimation pass found no reconstruction (%s)", exc)
        return False
    return calibration.add_suspects(probe.reports["triangulate"]["outlier_sigma_px_by_camera"], calibration.scene,
                                    lambda: output_scene(probe))


def _load_options(options: RunOptions, estimation: bool = False):
    """The load stage's options of a run; ``estimation``: with ESTIMATION_LOAD."""
    return replace(options.load, progress=options.progress, jobs=options.jobs,
                   **(ESTIMATION_LOAD if estimation else {}))


def _build_graph(input_path: str, kind: InputKind, scene: SfMScene, options: RunOptions,
                 estimation: bool = False, noise_sigma=NOT_MEASURED) -> Run:
    """The load stage's view graph of ``scene``; ``estimation``: for a pass that only
    estimates intrinsics (ESTIMATION_LOAD: one RANSAC run per edge, fewer trials);
    ``noise_sigma``: stages.load.measure_noise of this scene, if made already."""
    from rotonly_cli.stages.load import build_view_graph

    graph, report = build_view_graph(scene, _load_options(options, estimation), noise_sigma)
    run = Run(input_path, kind, scene, graph, options, reports={"load": report})
    _ensure_two_views(graph, "loading")
    return run


def identify_stage(run: Run) -> None:
    from rotonly_cli.stages.identify import identify_edges

    run.reports["identify"] = identify_edges(run.graph, run.scene.normalized, run.options.identification,
                                             jobs=run.options.jobs)
    _ensure_two_views(run.graph, "scene identification")


def refine_stage(run: Run) -> None:
    from rotonly_cli.stages.refine import refine_edges

    run.reports["refine"] = refine_edges(run.graph, run.scene.normalized, run.options.trrm,
                                         run.options.identification, jobs=run.options.jobs)
    _ensure_two_views(run.graph, "TRRM")


def average_stage(run: Run) -> None:
    from rotonly_cli.stages.average import average_graph

    run.rotations, run.reports["average"] = average_graph(run.graph, run.options.average)


def optimize_stage(run: Run) -> None:
    from rotonly_cli.stages.optimize import optimize_graph

    if not run.options.grrm:
        run.reports["optimize"] = {"skipped": "disabled (--no-grrm)"}
        return
    from rotonly_cli.runtime.progress import iteration_bar

    with iteration_bar(run.options.progress, run.options.optimize.max_iterations, "GRRM") as on_iteration:
        run.rotations, run.reports["optimize"] = optimize_graph(run.graph, run.scene.normalized, run.rotations,
                                                                run.options.optimize, on_iteration=on_iteration,
                                                                jobs=run.options.jobs)


def translate_stage(run: Run) -> None:
    from rotonly_cli.stages.translate import translate_graph

    run.centers, run.reports["translate"] = translate_graph(
        run.graph, run.scene.normalized, run.rotations, run.options.translate, track_cache=run.tracks,
        focal_px=run.scene.focal_px(run.graph.view_ids()), jobs=run.options.jobs)


def image_root(run: Run) -> Path | None:
    """--image-path; else COLMAP: ``images/`` beside the database; OpenMVG: root_path the way
    OpenMVG's tools read it (from the current directory), else from the sfm_data.json folder."""
    if run.options.image_path:
        return Path(run.options.image_path)
    input_path = Path(run.input_path)
    if run.input_kind == InputKind.COLMAP_DB:
        candidate = input_path.parent / "images"
        return candidate if input_path.is_file() and candidate.is_dir() else None
    if run.input_kind != InputKind.OPENMVG:
        return None
    from rotonly_cli.io.openmvg import image_root as openmvg_image_root

    return openmvg_image_root(run.scene.root_path, input_path / "sfm_data.json" if input_path.is_dir() else input_path)


def output_root_path(run: Run) -> str:
    """``root_path`` of OUT/sfm_data.json: --image-path as given, an OpenMVG input's root_path
    as it came (OpenMVG resolves both from the current directory), else the image folder found."""
    if run.options.image_path:
        return str(run.options.image_path)
    if run.input_kind == InputKind.OPENMVG:
        return run.scene.root_path
    root = image_root(run)
    return "" if root is None else str(root)


def reject_stage(run: Run) -> None:
    """Multi-view outlier rejection. First, when LiGT's solve says the rotations disagree with
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
            (optimize_stage if key == "optimize" else translate_stage)(run)  # looked up now: tests replace them
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
        # of the points it was resected from (castle-P19's OpenMVG matches, seed 4: judged with
        # them, the round's drops took the rotations 0.1099 -> 0.1153 deg)
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
        _ensure_two_views(run.graph, "multi-view rejection")
        resolve()
        off_after = list(views_off(run.reports.get("translate")))
        # views resected after the solve count as lost: the round's drops cut them out of the
        # tracks' rigid set, and their rotations are the ones those drops spoiled (castle-P19's
        # OpenMVG matches, focal x1.2: resected, the round kept, 0.0945 -> 0.1267 deg)
        lost = views_lost(before.reports["translate"], run.reports.get("translate"))
        if len(off_after) > len(views_off(before.reports["translate"])) or lost:
            # LiGT's solve on the cleaned tracks collapsed where the previous one had not (castle-P19,
            # OpenMVG matches, 5 consensus runs, seed 3: 17.6 GT units), or the dropped matches cut
            # views out of the set that tracks tie together (the same input, seed 1: views 12-15
            # lost their centres in the second round): the round is undone
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


def triangulate_stage(run: Run) -> None:
    from rotonly_cli.stages.triangulate import triangulate_graph

    run.structure, run.reports["triangulate"] = triangulate_graph(run.graph, run.scene, run.rotations, run.centers,
                                                                  image_root(run), run.options.triangulate,
                                                                  keypoint_rgb=run.keypoint_rgb,
                                                                  track_cache=run.tracks,
                                                                  outliers=run.options.translate)


STAGE_FUNCTIONS = {"identify": identify_stage, "refine": refine_stage, "average": average_stage,
                   "optimize": optimize_stage, "translate": translate_stage, "reject": reject_stage,
                   "triangulate": triangulate_stage}


# ============================================================================ intrinsics

def _chain(run: Run, stages: tuple[str, ...] | list[str]) -> Run:
    for stage in stages:
        STAGE_FUNCTIONS[stage](run)
    return run


#: a pass whose reconstruction only serves to estimate the intrinsics: the bundle adjustment
#: that follows moves every pose and point, so the RANSAC poses stand in for TRRM's, GRRM
#: and LiGT's robust rounds are left out (the estimates agree to 0.1 px: docs/tuning.md)
ESTIMATION_STAGES = ("identify", "average", "translate", "triangulate")
#: ... and when such a pass needs relative poses of its own (the intrinsics moved far since the
#: last load stage), one RANSAC run per edge with fewer trials will do: far from the right
#: intrinsics, RANSAC runs into its trial limit on every edge (docs/tuning.md)
ESTIMATION_LOAD = {"consensus_runs": 1, "ransac_max_trials": 500}


def _rerun(loaded: Run, scene: SfMScene, template: Run, estimation: bool = False, chain=_chain) -> Run:
    """The stages after load on ``scene`` (new intrinsics) from a copy of ``loaded``'s view
    graph: the edges, inlier matches and relative poses of its load stage, as the TRRM starts.
    ``template``: the run of the load stage (keypoint colours, calibration, load report).
    ``estimation``: only ESTIMATION_STAGES, with plain LiGT."""
    report = {**template.reports["load"], **loaded.reports["load"]}
    options = loaded.options
    if estimation:
        options = replace(options, translate=replace(options.translate, robust_rounds=0))
    run = Run(loaded.input_path, loaded.input_kind, scene, copy.deepcopy(loaded.graph), options,
              reports={"load": report}, keypoint_rgb=template.keypoint_rgb, calibration=template.calibration)
    return chain(run, ESTIMATION_STAGES if estimation else STAGES[1:])


def calibrated_chain(loaded: Run, chain=_chain) -> Run:
    """identify ... triangulate with the intrinsics calibrated (calibration/): passes
    of rotonly's stages, each followed by an estimate of the intrinsics from its
    reconstruction, until they settle; then the final pass, whose rotations, centres and
    points are the result. ``loaded``: the run after the load stage (not changed); ``chain``:
    runs stages on a run (:func:`_chain`; run_stages adds the progress bars)."""
    from rotonly_cli.options import Intrinsics

    calibration = loaded.calibration
    options = loaded.options.intrinsics
    if calibration is None or options.mode == Intrinsics.FIXED:
        return chain(loaded, STAGES[1:])
    guessed = bool(calibration.calibrate)
    started = time.perf_counter()
    run = _rerun(loaded, loaded.scene, loaded, estimation=guessed, chain=chain)
    auto = options.mode == Intrinsics.AUTO

    def judge_given(run: Run) -> bool:
        """auto: the cameras taken as given that ``run``'s reconstruction shows wrong join the
        calibration (suspects, then the centred principal points of the others); True if any did."""
        if all(camera_id in calibration.calibrate for camera_id in run.scene.intrinsics):
            return False  # every camera is calibrated already
        posed = functools.cache(lambda: output_scene(run))  # made only if some camera is checked
        suspects = calibration.add_suspects(run.reports["triangulate"]["outlier_sigma_px_by_camera"], run.scene,
                                            posed)
        return calibration.check_centred(posed) or suspects

    # a reconstruction made with a guess still uncalibrated bends every camera's errors with
    # it (Herz-Jesus-P8's OpenMVG project with one view's focal a guess: the given camera of
    # the other seven reprojected at 0.35 px > 0.31 px and was "calibrated" 0.9 % short):
    # with guesses, the given cameras are judged once the guesses have settled (the rounds)
    unjudged = auto and guessed
    if not guessed and not (auto and judge_given(run)):
        return run  # every camera fits: the intrinsics stay as given
    # auto, when only suspects are calibrated: the run with the given intrinsics, the result if
    # none of their changes turns out significant
    fallback = None if guessed else run
    if not guessed:
        started = time.perf_counter()  # that pass would have been the result: not the calibration's time
    graph_run, full_load = loaded, True  # the run whose load stage (relative poses) the passes reuse

    def reload(estimation: bool) -> Run:
        return _build_graph(loaded.input_path, loaded.input_kind, calibration.scene, loaded.options, estimation)

    if calibration.moved_from(graph_run.scene):
        graph_run, full_load = reload(True), False
    if calibration.scene is not run.scene:
        run = _rerun(graph_run, calibration.scene, loaded, estimation=True, chain=chain)
    round_, last_round = 0, options.max_rounds - 1
    while True:
        settled = calibration.estimate(output_scene(run))
        if fallback is not None and calibration.back_to_given():
            calibration.time_s += time.perf_counter() - started
            return fallback
        if settled and unjudged:  # the guesses settled: now the given cameras can be judged
            unjudged = False
            settled = not judge_given(run)
        if (settled or round_ >= last_round) and calibration.check_zoom():
            # images at another zoom got a camera of their own: rounds for it
            settled, last_round = False, round_ + options.max_rounds
        if settled or round_ >= last_round:
            break
        if calibration.moved_from(graph_run.scene):  # the load stage's RANSAC ran with other intrinsics
            graph_run, full_load = reload(True), False
        run = _rerun(graph_run, calibration.scene, loaded, estimation=True, chain=chain)
        round_ += 1
    if not settled and len(calibration.steps.rounds) > 1 and not calibration.splits:
        # the rounds ran out without settling: they oscillate about intrinsics that
        # reconstructions bent by wrong matches cannot fix (castle-P19 listed with the focal 15 %
        # short, its default-preset E matches: 1394.8 -> 1480.6 -> 1380.7 -> 1427.5 -> 1568.5 px,
        # true 1380.9; the last one written, 7.2 deg). The estimate of the round whose
        # adjustment converged on the most points is taken
        calibration.take_best_round()
    calibration.time_s += time.perf_counter() - started
    if not full_load or calibration.moved_from(graph_run.scene):
        graph_run = reload(False)
    return _rerun(graph_run, calibration.scene, loaded, chain=chain)


def output_scene(run: Run) -> SfMScene:
    """The input scene with the estimated poses (views with rotation and centre) and points."""
    from rotonly_cli.stages.export import posed_scene

    return posed_scene(run.scene, run.graph.view_ids(), run.rotations, run.centers, run.structure,
                       output_root_path(run) or None)
