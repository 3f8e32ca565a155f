"""`rotonly run`: the whole chain (chain/) into a workspace, and the workspace form of each stage.

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

import logging
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING

from rotonly_cli.chain import (  # noqa: F401 - re-exported: the chain's names as pipeline.* too
    STAGE_FUNCTIONS,
    STAGES,
    Run,
    average_stage,
    calibrated_chain,
    identify_stage,
    image_root,
    load_scene,
    load_stage,
    optimize_stage,
    output_root_path,
    output_scene,
    refine_stage,
    reject_stage,
    translate_stage,
    triangulate_stage,
)
from rotonly_cli.errors import InputError, write_error
from rotonly_cli.io import atomic
from rotonly_cli.io.atomic import check_replaceable
from rotonly_cli.io.detect import InputKind, detect_input
from rotonly_cli.io.readers import READERS
from rotonly_cli.io.workspace import (
    STATE_FILE,
    WorkspaceState,
    check_graph_fits,
    load_state,
    read_report,
    save_state,
    write_report,
    write_view_graph_json,
)
from rotonly_cli.options import RunOptions
from rotonly_cli.runtime import heartbeat, interrupts, memory
from rotonly_cli.runtime.startup import collector_paused
from rotonly_cli.scene.types import SfMScene

if TYPE_CHECKING:
    from rotonly_cli.calibration import Calibration

logger = logging.getLogger(__name__)
WORKSPACE_ENTRIES = {"sfm_data.json", "sparse", "view_graph.json", "reports", "run.log", STATE_FILE, "eval",
                     "report.html"}


# ============================================================================ outputs

def write_outputs(out_dir: Path, run: Run):
    """OUT/sfm_data.json (OpenMVG) and OUT/sparse/ (COLMAP binary model): (the scene written,
    a handle whose ``result()`` returns once sfm_data.json is written, which a forked child may
    still be doing: stages/export.write_outputs)."""
    from rotonly_cli.stages import export

    scene = output_scene(run)
    return scene, export.write_outputs(out_dir, scene, run.input_kind, run.options.jobs)


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
    """GT for --gt: a Strecha folder, an OpenMVG sfm_data.json or a COLMAP model (its poses:
    held through the run, and all the evaluation reads)."""
    from rotonly_cli.io.detect import read_scene

    return read_scene(path, field="--gt", poses_only=True)


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


def gt_warning(run: Run, evaluation: dict, summary: dict) -> None:
    """After :func:`summarize_outcome`, into ``summary["warnings"]`` and logged: --gt names few
    of the input's images, as a ground truth of another scene does."""
    from rotonly_cli.evaluation.quality import unmatched_warning

    warning = unmatched_warning(evaluation, [view.name for view in run.scene.views.values()])
    if warning:
        summary["warnings"] = [*summary.get("warnings", []), f"--gt: {warning}"]
        logger.warning("%s", summary["warnings"][-1])


# ============================================================================ OUT handling

def check_out_dir(out_dir: Path) -> None:
    """OUT may be new, empty, or a previous workspace (replaced); anything else: InputError."""
    from rotonly_cli.components import model_files

    check_replaceable(out_dir, WORKSPACE_ENTRIES | model_files(out_dir), "a rotonly workspace")


def check_input(input_path: Path) -> InputKind:
    """What can be checked of INPUT before anything is written: its kind (returned), and what
    io/readers.READERS checks of that kind (a database table by table; OpenMVG projects are
    checked as they are read)."""
    kind = detect_input(input_path)
    READERS[kind].check(input_path)
    return kind


class _LogFile(logging.FileHandler):
    """run.log: a write error is kept (and raised by _RunLog), not printed as a traceback; a
    MemoryError is raised to the code that logged; file names that are not UTF-8 are written with backslash escapes."""

    error: OSError | None = None

    def handleError(self, record: logging.LogRecord) -> None:
        error = sys.exc_info()[1]
        if isinstance(error, MemoryError):  # the run ends with one line (cli.main), not a "Logging error"
            raise  # noqa: PLE0704 - called inside emit()'s except block: the error being handled
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
    from rotonly_cli.components import reconstruct

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
        kind = check_input(input_path)  # before anything is made: a bad input leaves no folder behind
    start = time.perf_counter()
    # --cluster: reached (or started) before anything is written: exit 2 leaves no trace
    with cluster_session(options):
        guard = memory.MemoryGuard(options.max_memory_gb)
        staging = atomic.Staging(out_dir)  # parents made here are removed again by discard()
        try:
            with _RunLog(staging.new), collector_paused():
                logger.info("rotonly run %s -> %s", label or input_path, out_dir)
                run = run_stages(input_path, options, stages, kind, label, scratch=staging.scratch, guard=guard)
                reconstruct(run, run.components)  # the view graph's other parts (components.py)
                with heartbeat.heartbeat(not options.progress), heartbeat.task("export"), \
                        guard.stage("export", memory.scene_counts(run.scene, run.graph) if stages[-1] == "triangulate"
                                    else None):
                    summary = _written(out_dir, _finish, staging.new, out_dir, run, list(stages), start, gt, guard)
            # the CLI's exit code follows OUT from the instant it is the new workspace (Ctrl-C deferred
            # until the commit is done: io/atomic, runtime/interrupts)
            _written(out_dir, staging.commit, check_out_dir, interrupts.outcome_written)
        finally:
            staging.discard()
    return summary, run


def cluster_session(options: RunOptions):
    """The run's Dask session (runtime/cluster.py): the one open already, else a new one of
    ``options.cluster`` (a context manager yielding None without --cluster)."""
    from contextlib import nullcontext

    from rotonly_cli.runtime import cluster

    session = cluster.active()
    return nullcontext(session) if session is not None else cluster.session_for(options.cluster, options.progress)


def run_in_memory(input_path: str | Path | SfMScene, options: RunOptions = RunOptions(),
                  stages: tuple[str, ...] = STAGES, kind: InputKind | None = None, label: str | None = None,
                  observe: Callable[[str, Run], None] | None = None) -> Run:
    """:func:`run_stages` as `rotonly run` runs them (the collector paused), writing nothing."""
    if not isinstance(input_path, SfMScene):
        kind = check_input(Path(input_path))
    with collector_paused():
        return run_stages(input_path, options, stages, kind, label, guard=memory.MemoryGuard(options.max_memory_gb),
                          observe=observe)


def run_stages(input_path: str | Path | SfMScene, options: RunOptions = RunOptions(),
               stages: tuple[str, ...] = STAGES, kind: InputKind | None = None, label: str | None = None,
               scratch: Path | None = None, guard: memory.MemoryGuard | None = None,
               observe: Callable[[str, Run], None] | None = None) -> Run:
    """Run ``stages`` (a prefix of STAGES) in memory on INPUT (a path, or a scene already read;
    ``kind``: what it is, detected here for a path when not given; ``label``: a scene's name),
    with the progress bars (in a pipe, progress lines: runtime/heartbeat) and -v detail lines.
    ``scratch``: where a database's private copy is made (default: a temporary folder).
    ``guard``: the memory guard each stage passes first (runtime/memory; default: one of
    ``options.max_memory_gb``); its record goes to ``run.reports["memory"]``.
    ``observe(stage, run)``: called after each stage of each pass (the calibration's passes,
    then the chain's; the last call of a stage is the result's), to look at the run as it is
    then (rotonly bench strecha: the edges kept before GRRM); it must not change the run."""
    from rotonly_cli.components import split_off
    from rotonly_cli.monitor import StageMonitor
    guard = guard or memory.MemoryGuard(options.max_memory_gb)
    # --cluster: the per-pair and per-track work on Dask for the whole chain (runtime/cluster.py)
    with cluster_session(options) as session, \
            StageMonitor(stages, options.progress) as monitor, heartbeat.heartbeat(not options.progress):
        counts = None  # an OpenMVG project or a scene: counted once read (the stages after load)
        if not isinstance(input_path, SfMScene):
            kind = kind or detect_input(Path(input_path))
            if kind == InputKind.COLMAP_DB:  # a database can be counted before it is read
                counts = memory.database_counts(input_path)
        with monitor.stage("load"), heartbeat.task("load"), guard.stage("load", counts):
            if isinstance(input_path, SfMScene):
                run = load_scene(input_path, kind, label or "<in memory>", options)
            else:
                run = load_stage(input_path, options, scratch, kind)
            monitor.run = run
        if observe is not None:
            observe("load", run)
        loaded = run
        if "triangulate" in stages:
            # the images are decoded for the point colours while the rotation stages run (in
            # a forked child where that is safe: stages/triangulate.start_keypoint_colors)
            from rotonly_cli.stages.triangulate import start_keypoint_colors

            run.keypoint_rgb = start_keypoint_colors(run.scene, image_root(run))

        def chain(pass_run: Run, pass_stages: tuple[str, ...] | list[str]) -> Run:
            """Stages on a run of this load stage (a pass of the calibration, or the chain),
            each under the monitor."""
            monitor.run = pass_run  # the detail lines read this pass's reports
            for stage in pass_stages:
                if pass_run.keypoint_rgb is None:
                    pass_run.keypoint_rgb = loaded.keypoint_rgb
                counts = memory.scene_counts(pass_run.scene, pass_run.graph)
                rounds = pass_run.options.reject.max_rounds if stage == "reject" else None  # counted in stages/reject
                with monitor.stage(stage), heartbeat.task(stage, rounds), \
                        guard.stage(stage, counts, pass_run.options) as stage_options:
                    pass_run.options = stage_options  # LiGT's chunks made smaller to fit, or as they were
                    STAGE_FUNCTIONS[stage](pass_run)
                if observe is not None:
                    observe(stage, pass_run)
            return pass_run

        if "triangulate" in stages:
            parts = split_off(loaded)  # before the chain changes the load stage's graph in place
            run = calibrated_chain(run, chain)
        else:
            chain(run, stages[1:])
        if session is not None:
            run.reports["cluster"] = session.record()  # into reports/run.json (_finish)
    run.reports["resources"] = monitor.resources
    if "triangulate" in stages:
        run.components = parts  # reconstructed by run_into, which writes them
    run.reports["memory"] = guard.record()
    return run


def _written(out_dir: Path, write, *args, field: str | None = "-o"):
    """``write(*args)`` with an OSError turned into the one-line write error of OUT."""
    try:
        return write(*args)
    except OSError as exc:
        raise write_error(exc, out_dir, field) from None


def summarize_outcome(run: Run, scene: SfMScene, summary: dict) -> None:
    """Into ``summary`` (and run.reports): the intrinsics each camera started from and ended
    with (reports/intrinsics.json), the views left out of the outputs, and the run's warnings
    (the calibration's, those views, the baseline check of the centres, the edges on no cycle,
    the rotations the tracks refuted, the views a rejection round cut loose, the pairs' scatter
    about the final rotations), each also logged."""
    from rotonly_cli.calibration.rounds import run_summary
    from rotonly_cli.components import components_warning, views_in_other_models
    from rotonly_cli.stages.average import (
        pair_scatter_deg,
        pair_scatter_warning,
        unchecked_edges,
        unchecked_edges_warning,
    )
    from rotonly_cli.stages.load import unprojectable_warning
    from rotonly_cli.stages.reject import confirmation_warning, refutation_warning, undone_round_warning
    from rotonly_cli.stages.translate import baseline_warning, pure_rotation_warning, unregistered_warning

    if run.calibration is not None:
        run.reports["intrinsics"] = run.calibration.finish(scene)
        summary.update(run_summary(run.reports["intrinsics"]))
    bridges = unchecked_edges(run.graph, set(scene.poses))
    summary["edges_on_no_cycle"] = [list(pair) for pair in bridges]
    summary["pair_residual_deg_median"] = pair_scatter_deg(run.graph, scene.poses)
    elsewhere = views_in_other_models(run.components)  # registered in another component's model
    summary["unregistered_views"] = unregistered = [v for v in run.graph.view_ids()
                                                    if v not in scene.poses and v not in elsewhere]
    without_camera = {v for v in unregistered if run.scene.views[v].intrinsics_id not in run.scene.intrinsics}
    found = [unprojectable_warning(run.reports.get("load")),
             unregistered_warning(len(run.graph.view_ids()), unregistered, run.reports.get("translate"),
                                  without_camera),
             baseline_warning(run.reports.get("translate")), pure_rotation_warning(run.reports.get("translate")),
             unchecked_edges_warning(bridges),
             refutation_warning(run.reports.get("reject")), confirmation_warning(run.reports.get("reject")),
             undone_round_warning(run.reports.get("reject")),
             pair_scatter_warning(summary["pair_residual_deg_median"]), components_warning(run.components)]
    summary["warnings"] = summary.get("warnings", []) + [warning for warning in found if warning]
    for warning in summary["warnings"]:
        logger.warning("%s", warning)


def _finish(directory: Path, out_dir: Path, run: Run, done: list[str], start: float,
            gt: SfMScene | None, guard: memory.MemoryGuard | None = None) -> dict:
    """Write outputs of a finished chain into ``directory`` (which becomes ``out_dir``);
    ``gt``: the ground truth of ``run.options.gt`` (:func:`ground_truth_for`) or None;
    ``guard``: the run's memory guard, whose predictions and limit go into reports/run.json."""
    from rotonly_cli.components import summary_entries, write_models
    from rotonly_cli.evaluation.run_report import structure_statistics, write_run_report
    from rotonly_cli.runtime.invocation import command_line

    summary: dict = {"input": run.input_path, "stages": done, "options": asdict(run.options)}
    if command_line() is not None:
        summary["command"] = command_line()
    recorded = run.reports.pop("memory", None)  # in reports/run.json, not a report of its own
    if "cluster" in run.reports:  # --cluster: the tasks and bytes per stage (runtime/cluster.py)
        summary["cluster"] = run.reports.pop("cluster")
    scene = statistics = pending = None
    try:
        if done[-1] == "triangulate":
            started = time.perf_counter()
            scene, pending = write_outputs(directory, run)
            statistics = structure_statistics(scene, run.graph.view_ids())
            run.reports["export"] = {**statistics.report, "time_s": time.perf_counter() - started}
            summary.update(num_views=len(run.scene.views), num_registered=len(scene.poses),
                           num_points=0 if scene.structure is None else len(scene.structure.points))
            write_models(directory, run, run.components)
            main_views = (run.reports.get("load") or {}).get(  # a stage command: the graph's component
                "largest_component_views", len(run.graph.views) - len(run.graph.unregistered_views))
            summary["components"] = summary_entries({"num_views": main_views, "num_registered": len(scene.poses),
                                                     "num_points": summary["num_points"]}, run.components)
            if gt is not None:
                evaluation = evaluate_against(run.options.gt, gt, scene, directory / "eval",
                                              str(out_dir / "sfm_data.json"))
                summary["rotation_error_deg"] = evaluation.get("rotation_error_deg")
            summarize_outcome(run, scene, summary)
            if gt is not None:
                gt_warning(run, evaluation, summary)
        summary["num_active_edges"] = len(run.graph.active_edges())
        summary["time_s"] = time.perf_counter() - start
        if guard is not None or recorded is not None:
            summary["memory"] = guard.record() if guard is not None else recorded
        run.reports["run"] = summary
        write_workspace(directory, run, done)
        write_run_report(directory, run, scene, statistics, done)
    finally:
        if pending is not None:
            pending.result()  # sfm_data.json written (or its error raised) before OUT is complete
    logger.info("done in %.2f s: %s", summary["time_s"],
                ", ".join(f"{summary[k]} {k.removeprefix('num_').replace('_', ' ')}"
                          for k in ("num_registered", "num_points", "num_active_edges") if k in summary))
    return summary


# ============================================================================ stage subcommands

def _restored_calibration(scene: SfMScene, options: RunOptions, saved: dict) -> Calibration:
    """The intrinsics an earlier command of this workspace ended with (state.npz), on ``scene``."""
    from rotonly_cli.calibration import start_calibration
    from rotonly_cli.options import Intrinsics

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
        # the earlier stages' reports, as `rotonly run` hands them over (the reject stage reads
        # LiGT's: the views it left out, its misfit of the tracks); written back only if the
        # stage re-solves them
        given = {name: read_report(out_dir, name) for name in STAGES[:position]}
        run.reports.update({name: report for name, report in given.items() if report is not None})
        from rotonly_cli.monitor import StageMonitor

        guard = memory.MemoryGuard(options.max_memory_gb)
        with StageMonitor([stage], options.progress) as monitor, heartbeat.heartbeat(not options.progress):
            monitor.run = run
            with monitor.stage(stage), heartbeat.task(stage), \
                    guard.stage(stage, memory.scene_counts(run.scene, run.graph), run.options) as checked:
                run.options = checked
                STAGE_FUNCTIONS[stage](run)
        for name, report in given.items():
            if report is not None and run.reports.get(name) is report:
                del run.reports[name]  # not redone: reports/<name>.json stays as it is
        done = list(STAGES[:position + 1])
        if position < STAGES.index("average"):
            run.rotations = None  # stale: computed from the edges before this stage
        if position < STAGES.index("translate"):
            run.centers = None
        return _written(out_dir, _finish, out_dir, out_dir, run, done, start, gt, guard, field=None)
