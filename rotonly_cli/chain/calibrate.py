"""The calibration of ``--intrinsics`` (calibration/, algorithms.md §8) as a controller around
the chain: :func:`load_scene` puts the guesses, the view-graph focals and the quick probe for
wrong cameras before the plain load stage (chain.stages.load_graph), and
:func:`calibrated_chain` runs passes of the stages, each followed by an estimate of the
intrinsics, until they settle, then the final pass whose result is written."""

from __future__ import annotations

import copy
import functools
import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rotonly_cli.chain.run import Run, output_scene
from rotonly_cli.chain.stages import load_graph, load_options, run_chain
from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.io.detect import InputKind
from rotonly_cli.io.readers import READERS
from rotonly_cli.options import RunOptions
from rotonly_cli.scene.types import SfMScene
from rotonly_cli.stages import STAGES
from rotonly_cli.stages.load import NOT_MEASURED

if TYPE_CHECKING:
    from rotonly_cli.calibration import Calibration

logger = logging.getLogger(__name__)


def load_stage(input_path: str | Path, options: RunOptions, scratch: Path | None = None,
               kind: InputKind | None = None) -> Run:
    """INPUT read, then :func:`load_scene`; ``scratch``: where a database's private copy is made
    (the run's staging folder); ``kind``: INPUT's kind, when detected already."""
    from rotonly_cli.stages.load import input_files, read_input

    start = time.perf_counter()
    scene, kind = read_input(input_path, options.matches_dir, options.matches_file, scratch, kind)
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
    scene, guessed_views = guess_missing_cameras(scene, options.intrinsics.mode,
                                                 READERS[kind].openmvg_cameras)
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
        noise = measure_noise(scene, load_options(options))
        noise_time = time.perf_counter() - started
        started = time.perf_counter()
        if _probe_for_suspects(input_label, kind, calibration, options, noise):
            # other intrinsics: the load stage measures again; this measurement served the calibration
            noise = NOT_MEASURED
            calibration.time_s += noise_time
            noise_time = 0.0
        calibration.time_s += time.perf_counter() - started
    run = load_graph(input_label, kind, calibration.scene, options, noise_sigma=noise)
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
    camera joined the calibration. Calibrated inputs never probe."""
    if not isinstance(noise_sigma, float) or noise_sigma <= options.intrinsics.probe_noise_px:
        return False
    logger.info("intrinsics: the matches fit essential matrices at sigma %.2f px (> %.2f px): a quick estimation "
                "pass checks the cameras first", noise_sigma, options.intrinsics.probe_noise_px)
    try:
        probe = load_graph(input_label, kind, calibration.scene, options, noise_sigma, **ESTIMATION_LOAD)
        probe = _rerun(probe, calibration.scene, probe, estimation=True)
    except AlgorithmError as exc:  # the full chain decides, as without the probe
        logger.info("intrinsics: the quick estimation pass found no reconstruction (%s)", exc)
        return False
    return calibration.add_suspects(probe.reports["triangulate"]["outlier_sigma_px_by_camera"], calibration.scene,
                                    lambda: output_scene(probe))


#: a pass whose reconstruction only serves to estimate the intrinsics: the bundle adjustment
#: that follows moves every pose and point, so the RANSAC poses stand in for TRRM's, GRRM
#: and LiGT's robust rounds are left out (the estimates agree to 0.1 px: docs/tuning.md)
ESTIMATION_STAGES = ("identify", "average", "translate", "triangulate")
#: ... and when such a pass needs relative poses of its own (the intrinsics moved far since the
#: last load stage), one RANSAC run per edge with fewer trials will do: far from the right
#: intrinsics, RANSAC runs into its trial limit on every edge (docs/tuning.md)
ESTIMATION_LOAD = {"consensus_runs": 1, "ransac_max_trials": 500}


def _rerun(loaded: Run, scene: SfMScene, template: Run, estimation: bool = False, chain=run_chain) -> Run:
    """The stages after load on ``scene`` (new intrinsics) from a copy of ``loaded``'s view
    graph: the edges, inlier matches and relative poses of its load stage, as the TRRM starts.
    ``template``: the run of the load stage (keypoint colours, calibration, load report).
    ``estimation``: only ESTIMATION_STAGES, with plain LiGT."""
    report = {**template.reports["load"], **loaded.reports["load"]}
    options = loaded.options
    if estimation:
        options = replace(options, translate=replace(options.translate, robust_rounds=0))
    run = Run(loaded.input_path, loaded.input_kind, scene, loaded.graph.copy(), options,
              reports={"load": report}, keypoint_rgb=template.keypoint_rgb, calibration=template.calibration)
    return chain(run, ESTIMATION_STAGES if estimation else STAGES[1:])


def calibrated_chain(loaded: Run, chain=run_chain) -> Run:
    """identify ... triangulate with the intrinsics calibrated (calibration/): passes
    of rotonly's stages, each followed by an estimate of the intrinsics from its
    reconstruction, until they settle; then the final pass, whose rotations, centres and
    points are the result. ``loaded``: the run after the load stage (not changed); ``chain``:
    runs stages on a run (chain.stages.run_chain; pipeline.run_stages adds the progress bars)."""
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
    # it (a right camera beside it looks wrong): with guesses, the given cameras are judged
    # once the guesses have settled (the rounds)
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
        return load_graph(loaded.input_path, loaded.input_kind, calibration.scene, loaded.options,
                          **(ESTIMATION_LOAD if estimation else {}))

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
        # reconstructions bent by wrong matches cannot fix, and the last need not be the best.
        # The estimate of the round whose
        # adjustment converged on the most points is taken
        calibration.take_best_round()
    calibration.time_s += time.perf_counter() - started
    if not full_load or calibration.moved_from(graph_run.scene):
        graph_run = reload(False)
    result = _rerun(graph_run, calibration.scene, loaded, chain=chain)
    return no_worse_than_given(result, loaded, chain) if guessed else result


#: an estimation pass with the given intrinsics that reprojects this many times worse than
#: the calibrated result settles the comparison of no_worse_than_given: with the same
#: intrinsics such a pass reprojects within 3 % of a full one (docs/tuning.md "Cameras that
#: cannot be calibrated"); closer, a full pass with the given intrinsics decides
GIVEN_SCREEN_RATIO = 1.1
#: ... and the calibration is worse when its final pass reprojects more than this fraction
#: above the given intrinsics' full pass: the wall's shared focal 1000.7 px against the given
#: 1000 px differ by less (docs/tuning.md "Cameras that cannot be calibrated")
WORSE_THAN_GIVEN = 0.02


def _reprojection_sigma(run: Run) -> float:
    """The triangulate stage's robust sigma (px) of every observation's reprojection error
    before it drops any: the reconstruction's own cost, in the matches' units; inf without one."""
    sigma = run.reports.get("triangulate", {}).get("outlier_sigma_px")
    return float(sigma) if sigma is not None and np.isfinite(sigma) else float("inf")


def _registered(run: Run) -> int:
    return 0 if run.centers is None else int(np.all(np.isfinite(run.centers), axis=1).sum())


def no_worse_than_given(result: Run, loaded: Run, chain=run_chain) -> Run:
    """``result`` (the final pass with the calibrated intrinsics), or the run with every
    camera as given when that reconstruction registers as many views and reprojects better
    (:func:`_reprojection_sigma`, by more than WORSE_THAN_GIVEN): a calibration that makes
    the reconstruction worse than the given intrinsics is never written (issue 51; a wall
    seen by six images, a camera each: 1.50 px calibrated, 0.70 px given). First an
    estimation pass with the given intrinsics (ESTIMATION_LOAD, ESTIMATION_STAGES): where it
    reprojects GIVEN_SCREEN_RATIO times worse the calibration stands (a guess far off); else
    a full pass decides. No ground truth."""
    from rotonly_cli.calibration.rounds import same_intrinsics

    calibration = loaded.calibration
    if calibration.splits or calibration.back_to_given():
        return result
    started = time.perf_counter()
    given = calibration.given_scene()
    check = {"calibrated_sigma_px": _reprojection_sigma(result), "calibrated_registered": _registered(result)}
    given_run = None  # the full pass with the given intrinsics, when the screen asks for one
    try:
        graph = load_graph(loaded.input_path, loaded.input_kind, given, loaded.options, **ESTIMATION_LOAD)
        check["given_estimation_sigma_px"] = _reprojection_sigma(_rerun(graph, given, loaded, estimation=True,
                                                                        chain=chain))
    except AlgorithmError:  # no reconstruction with the given intrinsics
        check["given_estimation_sigma_px"] = float("inf")
    if check["calibrated_sigma_px"] * GIVEN_SCREEN_RATIO > check["given_estimation_sigma_px"]:
        # the load stage's relative poses serve if it ran with the given intrinsics (no
        # view-graph focal: as --intrinsics fixed would have run)
        same_load = all(c in loaded.scene.intrinsics and same_intrinsics(loaded.scene.intrinsics[c], k)
                        for c, k in given.intrinsics.items())
        graph = loaded if same_load else load_graph(loaded.input_path, loaded.input_kind, given, loaded.options)
        try:
            given_run = _rerun(graph, given, loaded, chain=chain)
        except AlgorithmError:
            pass
        if given_run is not None:
            check.update(given_sigma_px=_reprojection_sigma(given_run), given_registered=_registered(given_run))
            if (check["given_sigma_px"] * (1.0 + WORSE_THAN_GIVEN) < check["calibrated_sigma_px"]
                    and check["given_registered"] >= check["calibrated_registered"]):
                result = given_run
    check["time_s"] = time.perf_counter() - started
    calibration.time_s += check["time_s"]
    if result is given_run:
        calibration.back_to_given_after_check(check)
        return result
    calibration.steps.given_check = {**check, "reverted": False}
    logger.info("intrinsics: the calibrated reconstruction reprojects at sigma %.4f px, an estimation pass with the "
                "given intrinsics at %.4f px%s: the calibration is kept", check["calibrated_sigma_px"],
                check["given_estimation_sigma_px"],
                f", a full pass at {check['given_sigma_px']:.4f} px" if "given_sigma_px" in check else "")
    return result
