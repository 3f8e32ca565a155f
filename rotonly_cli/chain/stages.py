"""The stages of the chain in memory, each a function of the Run (the stage modules do the
work: stages/<name>.py), and the plain load stage of a scene whose intrinsics are settled.

load (INPUT -> view graph, re-estimated relative poses, min-inlier filter)
-> identify (scene kinds; ROTATION_SINGULAR filtered) -> refine (TRRM, batched)
-> average (L1-IRLS, gross-outlier filter) -> optimize (GRRM) -> translate (robust LiGT)
-> reject (multi-view outlier rejection, then GRRM + LiGT again) -> triangulate (+ colours).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

from rotonly_cli.chain.reject import rejection
from rotonly_cli.chain.run import Run, ensure_two_views, image_root
from rotonly_cli.io.detect import InputKind
from rotonly_cli.options import RunOptions
from rotonly_cli.scene.types import SfMScene
from rotonly_cli.stages.load import NOT_MEASURED

logger = logging.getLogger(__name__)


def load_options(options: RunOptions, **changes):
    """The load stage's options of a run (``changes``: LoadOptions fields set otherwise, an
    estimation pass's: chain/calibrate.ESTIMATION_LOAD)."""
    return replace(options.load, progress=options.progress, jobs=options.jobs, **changes)


def load_graph(input_label: str, kind: InputKind, scene: SfMScene, options: RunOptions,
               noise_sigma=NOT_MEASURED, **changes) -> Run:
    """The load stage on a scene whose intrinsics are settled: its view graph (relative poses
    re-estimated, the min-inlier filter), as a new Run; ``noise_sigma``: stages.load.measure_noise
    of this scene, if made already; ``changes``: as for :func:`load_options`."""
    from rotonly_cli.stages.load import build_view_graph

    graph, report = build_view_graph(scene, load_options(options, **changes), noise_sigma)
    run = Run(input_label, kind, scene, graph, options, reports={"load": report})
    ensure_two_views(graph, "loading")
    return run


def identify_stage(run: Run) -> None:
    from rotonly_cli.stages.identify import identify_edges

    run.reports["identify"] = identify_edges(run.graph, run.scene.normalized, run.options.identification,
                                             jobs=run.options.jobs)
    ensure_two_views(run.graph, "scene identification")


def refine_stage(run: Run) -> None:
    from rotonly_cli.stages.refine import refine_edges

    run.reports["refine"] = refine_edges(run.graph, run.scene.normalized, run.options.trrm,
                                         run.options.identification, jobs=run.options.jobs)
    ensure_two_views(run.graph, "TRRM")


def average_stage(run: Run) -> None:
    from rotonly_cli.stages.average import average_graph

    run.rotations, run.reports["average"] = average_graph(run.graph, run.options.average)
    if run.options.average.drop_minority_keypoints:
        # once, before GRRM and LiGT (the rejection's re-solves keep what is left)
        from rotonly_cli.scene.tracks import drop_minority_keypoint_matches

        started = time.perf_counter()
        report = drop_minority_keypoint_matches(run.graph, run.graph.active_edges())
        report["time_s"] = time.perf_counter() - started
        run.reports["average"]["minority_keypoints"] = report
        run.reports["average"]["time_s"] += report["time_s"]
        logger.info("average: %d of %d matches on a minority keypoint of their track dropped", report["num_dropped"],
                    report["num_matches"])


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


def reject_stage(run: Run) -> None:
    """Multi-view outlier rejection (chain/reject.rejection), each re-solve by the optimize and
    translate stages of STAGE_FUNCTIONS (looked up at each call: tests replace them)."""
    rejection(run, lambda name: STAGE_FUNCTIONS[name](run))


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


def run_chain(run: Run, stages: tuple[str, ...] | list[str]) -> Run:
    """``stages`` (names of STAGE_FUNCTIONS) on ``run``, in order."""
    for stage in stages:
        STAGE_FUNCTIONS[stage](run)
    return run
