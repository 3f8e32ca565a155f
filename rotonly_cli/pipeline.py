"""`rotonly run`: the whole chain, and the workspace form of each stage.

load (INPUT -> view graph, re-estimated relative poses, min-inlier filter)
-> identify (scene kinds; ROTATION_SINGULAR filtered) -> refine (TRRM, batched)
-> average (L1-IRLS, gross-outlier filter) -> optimize (GRRM) -> translate (robust LiGT)
-> reject (multi-view outlier rejection, then GRRM + LiGT again) -> triangulate (+ colours)
-> export (OUT/sfm_data.json, OUT/sparse/).

Every stage reads and writes plain objects; :class:`Run` holds them. The workspace
``OUT/`` (architecture.md "CLI contract"): ``sfm_data.json``, ``sparse/``, ``view_graph.json``,
``reports/<stage>.json``, ``run.log`` and ``state.npz`` (io/workspace.py) for the stage
subcommands. ``run`` builds the whole workspace in a staging folder beside OUT and swaps it
in at the end (io/atomic.Staging), so a failed or killed run leaves no partial OUT, and the
next run into OUT removes what a killed one left.

Errors: rotonly's own (errors.py) pass through; an OSError while writing becomes a one-line
write error (exit 1 for a full disk); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import copy
import logging
import sys
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rotonly_cli.errors import AlgorithmError, InputError, write_error
from rotonly_cli.io import atomic
from rotonly_cli.io.atomic import check_replaceable
from rotonly_cli.io.detect import InputKind, detect_input
from rotonly_cli.io.workspace import (
    STATE_FILE,
    WorkspaceState,
    check_graph_fits,
    load_state,
    save_state,
    write_report,
    write_view_graph_json,
)
from rotonly_cli.options import RunOptions
from rotonly_cli.runtime.startup import collector_paused
from rotonly_cli.scene.tracks import TrackCache
from rotonly_cli.scene.types import SfMScene, Structure
from rotonly_cli.scene.view_graph import ViewGraph, largest_component

if TYPE_CHECKING:
    from rotonly_cli.stages.intrinsics import Calibration

logger = logging.getLogger(__name__)
STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")
#: files a workspace may hold; an existing OUT with anything else is not replaced
WORKSPACE_ENTRIES = {"sfm_data.json", "sparse", "view_graph.json", "reports", "run.log", STATE_FILE, "eval",
                     "report.html"}


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
    #: the camera calibration of this run (stages/intrinsics.Calibration)
    calibration: Calibration | None = None


# ============================================================================ stages in memory

def _ensure_two_views(graph: ViewGraph, after: str) -> None:
    component = largest_component(graph)
    if len(component) < 2:
        usable = len(graph.views) - len(graph.unregistered_views)
        raise AlgorithmError(f"fewer than two usable images after {after} ({usable} of {len(graph.views)} "
                             f"connected by an edge); nothing to reconstruct")


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
    from rotonly_cli.stages.intrinsics import start_calibration

    started = time.perf_counter()
    calibration = start_calibration(scene, options.intrinsics, jobs=options.jobs)
    calibration.time_s += time.perf_counter() - started
    run = _build_graph(input_label, kind, calibration.scene, options)
    run.calibration = calibration
    run.input_intrinsics = copy.deepcopy(scene.intrinsics)
    run.reports["load"].update(read_time_s=read_time, input=input_label, input_kind=kind,
                               **(sources or {"input_files": []}))
    return run


def _build_graph(input_path: str, kind: InputKind, scene: SfMScene, options: RunOptions,
                 estimation: bool = False) -> Run:
    """The load stage's view graph of ``scene``; ``estimation``: for a pass that only
    estimates intrinsics (ESTIMATION_LOAD: one RANSAC run per edge, fewer trials)."""
    from rotonly_cli.stages.load import build_view_graph

    load = replace(options.load, progress=options.progress, jobs=options.jobs,
                   **(ESTIMATION_LOAD if estimation else {}))
    graph, report = build_view_graph(scene, load)
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
                                                                run.options.optimize, on_iteration=on_iteration)


def translate_stage(run: Run) -> None:
    from rotonly_cli.stages.translate import translate_graph

    run.centers, run.reports["translate"] = translate_graph(
        run.graph, run.scene.normalized, run.rotations, run.options.translate, track_cache=run.tracks,
        focal_px=run.scene.focal_px(run.graph.view_ids()))


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
    """Rounds of stages/reject (drop the matches inconsistent with the global poses) followed
    by GRRM and LiGT on what is left, until a round drops nothing (RejectOptions.max_rounds).
    The optimize and translate reports are those of the last solve."""
    from rotonly_cli.stages.reject import reject_round

    start = time.perf_counter()
    rounds = []
    focal_px = run.scene.focal_px(run.graph.view_ids())
    for _ in range(run.options.reject.max_rounds):
        if run.rotations is None or run.centers is None:
            break
        report = reject_round(run.graph, run.scene.normalized, run.rotations, run.centers, focal_px,
                              run.options.reject, run.options.load.min_inliers, run.options.average.max_residual_deg)
        rounds.append(report)
        logger.info("reject: %d of %d matches inconsistent with the global poses (threshold %.2f px), edges "
                    "filtered %s", report["num_dropped"], report["num_matches"], report["threshold_px"] or 0.0,
                    report["edges_filtered"] or "none")
        if report["num_dropped"] == 0 and not report["edges_filtered"]:
            break
        _ensure_two_views(run.graph, "multi-view rejection")
        optimize_stage(run)
        translate_stage(run)
    run.reports["reject"] = {"rounds": rounds, "num_dropped": int(sum(r["num_dropped"] for r in rounds)),
                             "time_s": time.perf_counter() - start}


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
    """identify ... triangulate with the intrinsics calibrated (stages/intrinsics.py): passes
    of rotonly's stages, each followed by an estimate of the intrinsics from its
    reconstruction, until they settle; then the final pass, whose rotations, centres and
    points are the result. ``loaded``: the run after the load stage (not changed); ``chain``:
    runs stages on a run (:func:`_chain`; run_stages adds the progress bars)."""
    from rotonly_cli.stages import intrinsics

    calibration = loaded.calibration
    options = loaded.options.intrinsics
    if calibration is None or options.mode == intrinsics.Mode.FIXED:
        return chain(loaded, STAGES[1:])
    guessed = bool(calibration.calibrate)
    started = time.perf_counter()
    run = _rerun(loaded, loaded.scene, loaded, estimation=guessed, chain=chain)
    suspects = options.mode == intrinsics.Mode.AUTO and calibration.add_suspects(
        run.reports["triangulate"]["outlier_sigma_px_by_camera"], run.scene)
    if not suspects and not guessed:
        return run  # every camera fits: the intrinsics stay as given
    if not guessed:
        calibration.fallback = run  # the result if no change turns out significant
        started = time.perf_counter()  # that pass would have been the result: not the calibration's time
    graph_run, full_load = loaded, True  # the run whose load stage (relative poses) the passes reuse

    def reload(estimation: bool) -> Run:
        return _build_graph(loaded.input_path, loaded.input_kind, calibration.scene, loaded.options, estimation)

    if calibration.moved_from(graph_run.scene):
        graph_run, full_load = reload(True), False
    if calibration.scene is not run.scene:
        run = _rerun(graph_run, calibration.scene, loaded, estimation=True, chain=chain)
    for round_ in range(options.max_rounds):
        settled = calibration.estimate(output_scene(run))
        if calibration.back_to_given():
            calibration.time_s += time.perf_counter() - started
            return calibration.fallback
        if settled or round_ == options.max_rounds - 1:
            break
        if calibration.moved_from(graph_run.scene):  # the load stage's RANSAC ran with other intrinsics
            graph_run, full_load = reload(True), False
        run = _rerun(graph_run, calibration.scene, loaded, estimation=True, chain=chain)
    calibration.time_s += time.perf_counter() - started
    if not full_load or calibration.moved_from(graph_run.scene):
        graph_run = reload(False)
    return _rerun(graph_run, calibration.scene, loaded, chain=chain)


# ============================================================================ outputs

def output_scene(run: Run) -> SfMScene:
    """The input scene with the estimated poses (views with rotation and centre) and points."""
    from rotonly_cli.stages.export import posed_scene

    return posed_scene(run.scene, run.graph.view_ids(), run.rotations, run.centers, run.structure,
                       output_root_path(run) or None)


def write_outputs(out_dir: Path, run: Run) -> SfMScene:
    """OUT/sfm_data.json (OpenMVG) and OUT/sparse/ (COLMAP binary model)."""
    from rotonly_cli.stages import export

    scene = output_scene(run)
    export.write_outputs(out_dir, scene, run.input_kind)
    return scene


def write_workspace(out_dir: Path, run: Run, stages_done: list[str]) -> None:
    """state.npz, view_graph.json and reports/<stage>.json of the stages run so far."""
    write_view_graph_json(out_dir / "view_graph.json", run.graph)
    for stage, report in run.reports.items():
        write_report(out_dir, stage, report)
    options = {"matches_dir": run.options.matches_dir, "matches_file": run.options.matches_file,
               "image_path": run.options.image_path, "grrm": run.options.grrm}
    intrinsics = run.calibration.changed() if run.calibration is not None else {}
    if intrinsics:  # calibrated intrinsics, for the stage commands (absent: the input's)
        options["intrinsics"] = intrinsics
    save_state(out_dir, WorkspaceState(run.input_path, run.input_kind, run.options.matches_dir,
                                       run.options.image_path, run.graph, run.rotations, run.centers,
                                       stages_done, options))


def load_ground_truth(path: str | Path) -> SfMScene:
    """GT for --gt: a Strecha folder, an OpenMVG sfm_data.json or a COLMAP model."""
    from rotonly_cli.io.detect import read_scene

    return read_scene(path, field="--gt")


def ground_truth_for(options: RunOptions, stages: tuple[str, ...] | list[str]) -> SfMScene | None:
    """The --gt scene when ``stages`` end with triangulation (the evaluated result), else None.
    Read before any stage runs, so that a mistyped path fails at once instead of after the
    whole chain, whose result would then be discarded with the failed run."""
    return load_ground_truth(options.gt) if options.gt and "triangulate" in stages else None


def evaluate_against(gt_path: str | Path, gt: SfMScene, estimate: SfMScene, report_dir: Path,
                     estimate_path: str) -> dict:
    """Evaluate ``estimate`` against ``gt`` (read from ``gt_path``) into ``report_dir``."""
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.evaluation.report import write_report as write_eval_report

    report = evaluate(gt, estimate)
    report.gt_path, report.estimate_path = str(gt_path), estimate_path
    write_eval_report(report, report_dir)
    rotation = report.rotation_error_deg
    logger.info("eval: %d of %d GT cameras estimated, rotation error mean %.4f deg, median %.4f deg",
                report.num_matched, report.num_gt, rotation.mean, rotation.median)
    return report.to_dict()


# ============================================================================ OUT handling

def check_out_dir(out_dir: Path) -> None:
    """OUT may be new, empty, or a previous workspace (replaced); anything else: InputError."""
    check_replaceable(out_dir, WORKSPACE_ENTRIES, "a rotonly workspace")


def check_input(input_path: Path) -> None:
    """What can be checked of INPUT before anything is written: its kind, and a database
    table by table (io/colmap/database_check). OpenMVG projects are checked as they are read."""
    if detect_input(input_path) == InputKind.COLMAP_DB:
        from rotonly_cli.io.colmap.database_check import check_database

        check_database(input_path)


class _LogFile(logging.FileHandler):
    """run.log: a write error is kept (and raised by _RunLog), not printed as a traceback;
    file names that are not UTF-8 are written with backslash escapes."""

    error: OSError | None = None

    def handleError(self, record: logging.LogRecord) -> None:
        error = sys.exc_info()[1]
        if self.error is None and isinstance(error, OSError):
            self.error = error


class _RunLog:
    """Log records of the run also go to ``<dir>/run.log`` (closed on exit)."""

    def __init__(self, directory: Path):
        self.path = directory / "run.log"
        try:
            self.handler = _LogFile(self.path, mode="a", encoding="utf-8", errors="backslashreplace")
        except OSError as exc:
            raise write_error(exc, self.path, field=None) from None
        self.handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.handler.setLevel(logging.DEBUG)
        self.root = logging.getLogger()

    def __enter__(self):
        self.previous_level = self.root.level
        self.root.addHandler(self.handler)
        if self.root.level > logging.INFO:  # run.log keeps INFO even under -q
            for handler in self.root.handlers:
                if handler is not self.handler and handler.level == logging.NOTSET:
                    handler.setLevel(self.root.level)
            self.root.setLevel(logging.INFO)
        return self

    def __exit__(self, kind, *exc):
        self.root.removeHandler(self.handler)
        self.root.setLevel(self.previous_level)
        self.handler.close()
        if kind is None and self.handler.error is not None:
            raise write_error(self.handler.error, self.path, field=None)


def run_pipeline(input_path: str | Path, out_dir: str | Path, options: RunOptions = RunOptions(),
                 stages: tuple[str, ...] = STAGES) -> dict:
    """Run ``stages`` (a prefix of STAGES) on INPUT into OUT, atomically; returns the summary.

    With all stages the outputs (sfm_data.json, sparse/) are written, and with
    ``options.gt`` the evaluation (OUT/eval/report.{json,html}).
    """
    return run_into(input_path, out_dir, options, stages)[0]


def run_into(input_path: str | Path | SfMScene, out_dir: str | Path, options: RunOptions = RunOptions(),
             stages: tuple[str, ...] = STAGES, kind: InputKind | None = None,
             label: str | None = None) -> tuple[dict, Run]:
    """:func:`run_pipeline`, returning the run too; INPUT may be a scene already read (then
    ``kind`` and ``label`` say what it is, as for :func:`run_stages`)."""
    out_dir = Path(out_dir)
    in_memory = isinstance(input_path, SfMScene)
    if in_memory:
        label = label or "<in memory>"
    else:
        input_path = Path(input_path)
        if out_dir.exists() and input_path.resolve().is_relative_to(out_dir.resolve()):
            raise InputError("the input lies inside OUT, which would be replaced", path=str(input_path), field="-o")
    check_out_dir(out_dir)
    gt = ground_truth_for(options, stages)
    if not in_memory:
        check_input(input_path)  # before anything is made: a bad input leaves no folder behind
    staging = atomic.Staging(out_dir)  # parents made here are removed again by discard()
    start = time.perf_counter()
    try:
        with _RunLog(staging.new), collector_paused():
            logger.info("rotonly run %s -> %s", label or input_path, out_dir)
            run = run_stages(input_path, options, stages, kind, label, scratch=staging.scratch)
            summary = _written(out_dir, _finish, staging.new, out_dir, run, list(stages), start, gt)
        _written(out_dir, staging.commit, check_out_dir)
    finally:
        staging.discard()
    return summary, run


def run_in_memory(input_path: str | Path | SfMScene, options: RunOptions = RunOptions(),
                  stages: tuple[str, ...] = STAGES, kind: InputKind | None = None, label: str | None = None) -> Run:
    """:func:`run_stages` as `rotonly run` runs them (the collector paused), writing nothing."""
    if not isinstance(input_path, SfMScene):
        check_input(Path(input_path))
    with collector_paused():
        return run_stages(input_path, options, stages, kind, label)


def colours_start_after(run: Run, stages: tuple[str, ...] | list[str]) -> str | None:
    """The stage after which the images are decoded for the point colours (on a thread):
    right after loading, so that decoding overlaps the rotation stages, unless identification
    and TRRM will fork (``--jobs``, runtime/parallel): a fork waits for no running thread, so
    then after TRRM. None when the chain ends before triangulation."""
    if "triangulate" not in stages:
        return None
    from rotonly_cli.runtime.parallel import would_fork

    matches = sum(run.graph.edges[k].num_inliers for k in run.graph.active_edges())
    return "refine" if "refine" in stages and would_fork(matches, run.options.jobs) else "load"


def run_stages(input_path: str | Path | SfMScene, options: RunOptions = RunOptions(),
               stages: tuple[str, ...] = STAGES, kind: InputKind | None = None, label: str | None = None,
               scratch: Path | None = None) -> Run:
    """Run ``stages`` (a prefix of STAGES) in memory on INPUT (a path, or a scene already read:
    then ``kind`` and ``label`` say what it is), with the progress bars and -v detail lines.
    ``scratch``: where a database's private copy is made (default: a temporary folder)."""
    from rotonly_cli.monitor import StageMonitor

    with StageMonitor(stages, options.progress) as monitor:
        with monitor.stage("load"):
            if isinstance(input_path, SfMScene):
                run = load_scene(input_path, kind, label or "<in memory>", options)
            else:
                run = load_stage(input_path, options, scratch)
            monitor.run = run
        loaded, colours_after = run, colours_start_after(run, stages)

        def chain(pass_run: Run, pass_stages: tuple[str, ...] | list[str]) -> Run:
            """Stages on a run of this load stage (a pass of the calibration, or the chain),
            each under the monitor; the colours decoded once, after ``colours_after``."""
            monitor.run = pass_run  # the detail lines read this pass's reports
            for stage in pass_stages:
                if pass_run.keypoint_rgb is None:
                    pass_run.keypoint_rgb = loaded.keypoint_rgb
                with monitor.stage(stage):
                    STAGE_FUNCTIONS[stage](pass_run)
                if stage == colours_after and loaded.keypoint_rgb is None:
                    from rotonly_cli.stages.triangulate import start_keypoint_colors

                    loaded.keypoint_rgb = start_keypoint_colors(loaded.scene, image_root(loaded))
            return pass_run

        if colours_after == "load":
            from rotonly_cli.stages.triangulate import start_keypoint_colors

            run.keypoint_rgb = start_keypoint_colors(run.scene, image_root(run))
        if "triangulate" in stages:
            run = calibrated_chain(run, chain)
        else:
            chain(run, stages[1:])
    return run


def _written(out_dir: Path, write, *args, field: str | None = "-o"):
    """``write(*args)`` with an OSError turned into the one-line write error of OUT."""
    try:
        return write(*args)
    except OSError as exc:
        raise write_error(exc, out_dir, field) from None


def _finish(directory: Path, out_dir: Path, run: Run, done: list[str], start: float,
            gt: SfMScene | None) -> dict:
    """Write outputs of a finished chain into ``directory`` (which becomes ``out_dir``);
    ``gt``: the ground truth of ``run.options.gt`` (:func:`ground_truth_for`) or None."""
    from rotonly_cli.evaluation.run_report import structure_statistics, write_run_report

    summary: dict = {"input": run.input_path, "stages": done}
    scene = statistics = None
    if done[-1] == "triangulate":
        started = time.perf_counter()
        scene = write_outputs(directory, run)
        statistics = structure_statistics(scene, run.graph.view_ids())
        run.reports["export"] = {**statistics.report, "time_s": time.perf_counter() - started}
        summary.update(num_views=len(run.scene.views), num_registered=len(scene.poses),
                       num_points=0 if scene.structure is None else len(scene.structure.points),
                       unregistered_views=[v for v in run.graph.view_ids() if v not in scene.poses])
        if gt is not None:
            evaluation = evaluate_against(run.options.gt, gt, scene, directory / "eval",
                                          str(out_dir / "sfm_data.json"))
            summary["rotation_error_deg"] = evaluation.get("rotation_error_deg")
        if run.calibration is not None:
            run.reports["intrinsics"] = run.calibration.finish(scene)
            summary.update(run.calibration.summary())
            for warning in summary["warnings"]:
                logger.warning("%s", warning)
    summary["num_active_edges"] = len(run.graph.active_edges())
    summary["time_s"] = time.perf_counter() - start
    run.reports["run"] = summary
    write_workspace(directory, run, done)
    write_run_report(directory, run, scene, statistics, done)
    logger.info("done in %.2f s: %s", summary["time_s"],
                ", ".join(f"{summary[k]} {k.removeprefix('num_').replace('_', ' ')}"
                          for k in ("num_registered", "num_points", "num_active_edges") if k in summary))
    return summary


# ============================================================================ stage subcommands

def _restored_calibration(scene: SfMScene, options: RunOptions, saved: dict) -> Calibration:
    """The intrinsics an earlier command of this workspace ended with (state.npz), on ``scene``."""
    from rotonly_cli.options import Intrinsics
    from rotonly_cli.stages.intrinsics import start_calibration

    mode = saved.get("mode", Intrinsics.FIXED)
    calibration = start_calibration(scene, replace(options.intrinsics, mode=mode), calibrate_now=False)
    calibration.restore(saved)
    return calibration

def resume(out_dir: str | Path, stage: str, options: RunOptions | None = None) -> dict:
    """Run one stage on an existing workspace (``rotonly refine|average|... OUT``) in place.

    The stage's predecessors must be done; later stages' results become stale and are
    dropped from the state. Files are replaced one by one, each atomically.
    """
    from rotonly_cli.stages.load import read_input

    out_dir = Path(out_dir)
    state = load_state(out_dir)
    position = STAGES.index(stage)
    previous = STAGES[position - 1]
    if previous not in state.stages:
        raise InputError(f"stage {stage!r} needs {previous!r} first (done: {', '.join(state.stages)})",
                         path=str(out_dir))
    saved = state.options
    options = options or RunOptions()
    options = replace(options, matches_dir=options.matches_dir or saved.get("matches_dir"),
                      matches_file=options.matches_file or saved.get("matches_file"),
                      image_path=options.image_path or saved.get("image_path"))
    gt = ground_truth_for(options, [stage])
    start = time.perf_counter()
    with _RunLog(out_dir), collector_paused():
        with atomic.scratch_dir(out_dir) as scratch:  # a database's private copy, beside OUT
            scene, kind = read_input(state.input_path, options.matches_dir, options.matches_file, scratch)
        check_graph_fits(state.graph, scene, out_dir / STATE_FILE)
        calibration = _restored_calibration(scene, options, saved.get("intrinsics", {}))
        run = Run(state.input_path, kind, calibration.scene, state.graph, options, state.rotations,
                  state.centers, calibration=calibration)
        if stage == "triangulate" and (run.rotations is None or run.centers is None):
            raise InputError("no rotations / centres in the workspace", path=str(out_dir))
        from rotonly_cli.monitor import StageMonitor

        with StageMonitor([stage], options.progress) as monitor:
            monitor.run = run
            with monitor.stage(stage):
                STAGE_FUNCTIONS[stage](run)
        done = list(STAGES[:position + 1])
        if position < STAGES.index("average"):
            run.rotations = None  # stale: computed from the edges before this stage
        if position < STAGES.index("translate"):
            run.centers = None
        return _written(out_dir, _finish, out_dir, out_dir, run, done, start, gt, field=None)
