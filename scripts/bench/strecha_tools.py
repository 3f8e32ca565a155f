"""Strecha scenes: rotonly against the tools it replaces (pycolmap's global mapper, OpenMVG's
global SfM), timed as their users run them and scored by one evaluator.

Usage: python scripts/bench/strecha_tools.py --root DATA/strecha [--scenes fountain-P11 ...]
                                       [-o RESULTS_DIR] [--threads N] [--skip-mapper]
                                       [--openmvg-bin OPENMVG_BIN] [--timing-rounds N]
                                       [--results-md docs/results.md]

(``rotonly bench strecha`` is the other Strecha benchmark: the paper's per-pair and global
tables with the baselines.)

For every scene folder under ROOT (database.db, gt_dense_cameras/, openmvg/{sfm_data.json,
matches.e.bin, global/sfm_data.json}; data/strecha/README.md), in the same run:

* ``rotonly run <scene>/database.db`` and ``rotonly run <scene>/openmvg/sfm_data.json`` as a
  subprocess of the installed CLI (honest wall time, process start included), plus the
  internal stage times from OUT/reports/<stage>.json. The package is byte-compiled first, as
  ``pip install`` does for a regular install (this machine sets PYTHONDONTWRITEBYTECODE, which
  would otherwise make every run re-compile rotonly's sources, 0.1-0.2 s);
* the same two inputs once more in-process, stage by stage, to evaluate the GRRM start (the
  L1-IRLS averaged rotations, stage ``average``) against the GRRM result (stage ``optimize``),
  and pycolmap's rotation averaging on exactly rotonly's edges after TRRM (same edges, other
  averager);
* pycolmap rotation averaging on the database's stored two-view geometries (uniform and
  inlier-weighted: ``RotationAveragingReweighting.INLIER_MATCH_COUNT``), as the README's rows;
* pycolmap's global mapper (GLOMAP: rotation averaging + global positioning + BA, K fixed) on
  a private copy of the database, in a child process: the table's time is the global_mapping
  call (the data README's measure); the child's whole wall time is kept too, and each scene
  ends with rotonly's time ratio over both;
* OpenMVG 2.1's own global SfM result stored in openmvg/global/sfm_data.json (its time is the
  README's, whole seconds as OpenMVG prints them); with ``--openmvg-bin DIR`` also OpenMVG's
  global SfM re-run here on a copy of the same matches, its process wall time measured like
  rotonly's, once as stored (its BA refines the intrinsics) and once with the intrinsics held
  (``-f NONE``: K fixed, as rotonly and the mapper run);
* with ``--timing-rounds N``: ``rotonly run`` against the mapper on the database and against
  OpenMVG (default settings) on the OpenMVG matches, N alternating rounds each, with the
  ratio of the median times (one pair of runs moves by ±15 % here);
* a reference row per rotonly run: pycolmap's bundle adjustment (K fixed) started from
  rotonly's own ``OUT/sparse`` model, i.e. where BA's optimum lies on exactly rotonly's
  tracks (not a method of rotonly: it shows how far GRRM's optimum is from BA's).

One evaluator for all: ``rotonly_cli.evaluation.quality.evaluate`` against
``rotonly_cli.io.detect.read_ground_truth(scene)``: rotation error (geodesic after the best
global rotation, the README's metric; mean and OpenMVG's upper median), position error after the
similarity on centres (GT units; "–" for rotation-only estimates), number registered, time.
Writes RESULTS_DIR/results.json and RESULTS_DIR/table.md atomically; never writes into ROOT
(every database is copied to a temporary folder before pycolmap opens it).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.bench import results_md
from rotonly_cli.bench.common import code_version
from rotonly_cli.evaluation.quality import evaluate
from rotonly_cli.io import detect, openmvg
from rotonly_cli.scene.types import Pose, SfMScene, View

#: OpenMVG 2.1 global SfM wall time on this machine type (data/strecha/README.md, "What the
#: references reach"); the stored result is evaluated, the tool is not re-run.
OPENMVG_GLOBAL_TIME_S = {"fountain-P11": 5.0, "Herz-Jesus-P8": 1.0, "entry-P10": 2.0}
STAGE_NAMES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


@dataclass
class MethodResult:
    method: str
    rotation_mean_deg: float | None = None
    rotation_median_deg: float | None = None
    position_mean: float | None = None  # GT units, after the similarity on centres
    num_registered: int = 0
    num_gt: int = 0
    time_s: float | None = None
    time_note: str = ""  # how time_s was measured
    error: str = ""  # why the method produced nothing
    extra: dict = field(default_factory=dict)


# ============================================================================ evaluation

def evaluate_scene(method: str, gt: SfMScene, estimate: SfMScene, time_s: float | None,
                   time_note: str = "") -> MethodResult:
    """The one evaluator, applied to any estimate with poses keyed by view id and view names."""
    result = MethodResult(method, num_gt=len(gt.poses), time_s=time_s, time_note=time_note)
    if not estimate.poses:
        result.error = "no pose estimated"
        return result
    report = evaluate(gt, estimate)
    result.rotation_mean_deg = report.rotation_error_deg.mean
    result.rotation_median_deg = report.rotation_error_deg.median
    result.position_mean = None if report.position_error is None else report.position_error.mean
    result.num_registered = report.num_matched
    return result


def rotations_scene(names: dict[int, str], rotations: dict[int, np.ndarray],
                    centers: dict[int, np.ndarray] | None = None) -> SfMScene:
    """SfMScene holding only named views and poses. Without centres they are all zero, which
    the evaluator recognises as rotation-only (position metrics omitted)."""
    scene = SfMScene(source="bench")
    for view_id, R in rotations.items():
        if not np.all(np.isfinite(R)):
            continue
        scene.views[view_id] = View(view_id, names[view_id], 0)
        center = np.zeros(3) if centers is None else np.asarray(centers[view_id], dtype=float)
        scene.poses[view_id] = Pose(np.asarray(R, dtype=float), center)
    return scene


# ============================================================================ rotonly



def quiet_pycolmap(level: int = 2) -> int:
    """glog INFO lines ("Marked 0 image pairs as invalid ...") would drown the tables; 2 = errors
    and fatal only. Returns the previous level."""
    import pycolmap

    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    return previous


def rotonly_command() -> list[str]:
    """The console script of this interpreter's environment, else the one on PATH, else the
    click entry point run by this interpreter (the package has no ``__main__``)."""
    beside = Path(sys.executable).parent / "rotonly"
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside)]
    exe = shutil.which("rotonly")
    if exe:
        return [exe]
    return [sys.executable, "-c", "from rotonly_cli.cli import console_main; console_main()"]


def rotonly_run_command(input_path: Path, out: Path) -> list[str]:
    """``rotonly -q run INPUT -o OUT``, the way every rotonly row is timed."""
    return rotonly_command() + ["-q", "run", str(input_path), "-o", str(out)]


def byte_compile_rotonly() -> None:
    """Write rotonly's .pyc files (what ``pip install`` does at install time; an editable install
    under PYTHONDONTWRITEBYTECODE never gets them, and each subprocess would compile the sources)."""
    import compileall

    import rotonly_cli

    compileall.compile_dir(Path(rotonly_cli.__file__).parent, quiet=1)


def rotonly_out_dir(work: Path, method: str) -> Path:
    """OUT of the ``rotonly run`` row ``method`` (the BA reference reads its sparse/ model)."""
    return work / method.replace(" ", "_").replace("/", "_")


def run_rotonly_subprocess(method: str, input_path: Path, gt: SfMScene, work: Path, log_dir: Path) -> MethodResult:
    """`rotonly -q run INPUT -o OUT` as a subprocess; wall time and OUT/reports stage times."""
    out = rotonly_out_dir(work, method)
    command = rotonly_run_command(input_path, out)
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    completed = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
    (log_dir / f"{out.name}.log").write_text(f"$ {' '.join(command)}\nexit {completed.returncode}\n"
                                             f"--- stdout\n{completed.stdout}--- stderr\n{completed.stderr}")
    if completed.returncode != 0:
        result = MethodResult(method, num_gt=len(gt.poses), time_s=wall, time_note="subprocess wall")
        result.error = f"exit {completed.returncode}: {completed.stderr.strip().splitlines()[-1:]}"
        return result
    estimate = openmvg.read_sfm_data(out / "sfm_data.json")
    result = evaluate_scene(method, gt, estimate, wall, "subprocess wall")
    result.extra["subprocess_cpu_s"] = cpu  # user + sys of the child: less sensitive to other load
    stage_times = {}
    for stage in STAGE_NAMES + ("run",):
        report_path = out / "reports" / f"{stage}.json"
        if report_path.is_file():
            stage_times[stage] = json.loads(report_path.read_text()).get("time_s")
    result.extra["stage_times_s"] = stage_times
    optimize_report = out / "reports" / "optimize.json"
    if optimize_report.is_file():
        report = json.loads(optimize_report.read_text())
        result.extra["grrm"] = {k: report.get(k) for k in ("num_views", "num_edges", "num_matches", "iterations",
                                                           "cost_before", "cost_after", "converged")}
    return result


def run_rotonly_stages(label: str, input_path: Path, gt: SfMScene) -> tuple[list[MethodResult], dict]:
    """load..optimize in-process: the averaged (GRRM start) and GRRM rotations, and pycolmap
    rotation averaging on the same active edges after TRRM."""
    from rotonly_cli.pipeline import RunOptions, average_stage, identify_stage, load_stage, optimize_stage, refine_stage
    from rotonly_cli.scene.view_graph import view_index

    times: dict[str, float] = {}
    start = time.perf_counter()
    run = load_stage(input_path, RunOptions())
    times["load"] = time.perf_counter() - start
    for name, stage in (("identify", identify_stage), ("refine", refine_stage)):
        start = time.perf_counter()
        stage(run)
        times[name] = time.perf_counter() - start
    names = {v: run.graph.views[v].name for v in run.graph.view_ids()}
    index = view_index(run.graph)
    row_to_view = {row: v for v, row in index.items()}

    # pycolmap on rotonly's edges after TRRM (before the average stage filters outliers)
    edges = run.graph.active_edges()
    edge_views = np.array([[index[run.graph.edges[k].i], index[run.graph.edges[k].j]] for k in edges])
    R_j_from_i = np.stack([run.graph.edges[k].R_j_from_i for k in edges])
    inliers = np.array([run.graph.edges[k].num_inliers for k in edges])
    results = pycolmap_ra_results((f"pycolmap RA on rotonly's TRRM edges ({label})",
                                   f"pycolmap RA on rotonly's TRRM edges ({label}, inlier-weighted)"),
                                  [row_to_view[r] for r in range(len(index))], names, edge_views, R_j_from_i,
                                  inliers, gt)

    start = time.perf_counter()
    average_stage(run)
    times["average"] = time.perf_counter() - start
    averaged = run.rotations.copy()
    start = time.perf_counter()
    optimize_stage(run)
    times["optimize"] = time.perf_counter() - start
    start_result = evaluate_scene(f"rotonly L1-IRLS average = GRRM start ({label})", gt,
                                  rotations_scene(names, {row_to_view[r]: averaged[r] for r in range(len(averaged))}),
                                  times["load"] + times["identify"] + times["refine"] + times["average"],
                                  "in-process load..average")
    final_result = evaluate_scene(f"rotonly GRRM, in-process ({label})", gt,
                                  rotations_scene(names, {row_to_view[r]: run.rotations[r]
                                                          for r in range(len(run.rotations))}),
                                  sum(times.values()), "in-process load..optimize")
    final_result.extra["stage_times_s"] = times
    return [start_result, final_result] + results, times


# ============================================================================ pycolmap

def pycolmap_ra_results(method_names: tuple[str, str], row_views: list[int], names: dict[int, str],
                        edge_views: np.ndarray, R_j_from_i: np.ndarray, num_inliers: np.ndarray,
                        gt: SfMScene) -> list[MethodResult]:
    """``pycolmap.run_rotation_averaging`` (algorithms.md §2.3, default options: Geman-McClure,
    σ = 5°) uniform and with ``reweighting = INLIER_MATCH_COUNT`` (``method_names`` in that
    order), each evaluated; rows of the estimate are the views ``row_views``."""
    from rotonly_cli.baselines.references import pycolmap_rotation_averaging

    results = []
    for method, weighted in zip(method_names, (False, True)):
        start = time.perf_counter()
        R = pycolmap_rotation_averaging(len(row_views), edge_views, R_j_from_i,
                                        num_matches=np.asarray(num_inliers), weighted=weighted)
        elapsed = time.perf_counter() - start
        result = evaluate_scene(method, gt, rotations_scene(names, {row_views[r]: R[r] for r in range(len(R))}),
                                elapsed, "averaging call only")
        result.extra["num_edges"] = len(edge_views)
        results.append(result)
    return results


def run_pycolmap_stored(database: Path, gt: SfMScene) -> list[MethodResult]:
    """pycolmap RA on the database's stored cam2_from_cam1 (the README's first two rows)."""
    from rotonly_cli.io.colmap import read_database

    scene = read_database(database)  # reads a private copy of the file
    view_ids = sorted(scene.views)
    index = {v: k for k, v in enumerate(view_ids)}
    keys = [key for key in sorted(scene.pairs) if scene.pairs[key].verified and scene.pairs[key].R_j_from_i is not None]
    edge_views = np.array([[index[i], index[j]] for i, j in keys])
    R_j_from_i = np.stack([scene.pairs[key].R_j_from_i for key in keys])
    inliers = np.array([len(scene.pairs[key].matches) for key in keys])
    names = {v: scene.views[v].name for v in view_ids}
    return pycolmap_ra_results(("pycolmap RA on the stored two-view geometries",
                                "pycolmap RA on the stored two-view geometries (inlier-weighted)"),
                               view_ids, names, edge_views, R_j_from_i, inliers, gt)


def _mapper_worker(database: str, out: str, threads: str, seed: str) -> int:
    """Child process of run_global_mapper: pycolmap.global_mapping (GLOMAP) on ``database``,
    intrinsics fixed (formats.md §4.7); writes the largest model to OUT/best and prints the
    call's own time as JSON. Run as a process so that its whole wall time (interpreter,
    imports, database reading) is measured the way ``rotonly run``'s is."""
    import pycolmap

    pycolmap.logging.minloglevel = 2
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = int(seed)
    options.num_threads = int(threads)
    options.mapper.random_seed = int(seed)
    options.mapper.num_threads = int(threads)
    options.mapper.bundle_adjustment.refine_focal_length = False
    options.mapper.bundle_adjustment.refine_principal_point = False
    options.mapper.bundle_adjustment.refine_extra_params = False
    work = Path(out)
    (work / "images").mkdir(parents=True)  # must exist; the images are not read
    (work / "models").mkdir()
    start = time.perf_counter()
    models = pycolmap.global_mapping(Path(database), work / "images", work / "models", options)
    call = time.perf_counter() - start
    if models:
        best = max(models.values(), key=lambda r: r.num_reg_images())
        (work / "best").mkdir()
        best.write(str(work / "best"))
    print(json.dumps({"call_s": call, "num_models": len(models)}))
    return 0


def mapper_worker_command(database: Path, out: Path, threads: int, seed: int) -> list[str]:
    """This script as the _mapper_worker process on ``database`` (a private copy) into ``out``."""
    return [sys.executable, str(Path(__file__).resolve()), "--mapper-worker", str(database), str(out), str(threads),
            str(seed)]


def mapper_time_note(threads: int) -> str:
    return f"global_mapping call, {threads if threads > 0 else 'all'} threads"


def reconstruction_scene(rec) -> SfMScene:
    """The posed images of a pycolmap Reconstruction (rotation, centre, name) for the evaluator."""
    rotations, centers, names = {}, {}, {}
    for image in rec.images.values():
        if image.has_pose:
            rotations[image.image_id] = np.asarray(image.cam_from_world().rotation.matrix())
            centers[image.image_id] = np.asarray(image.projection_center())
            names[image.image_id] = image.name
    return rotations_scene(names, rotations, centers)


def run_ba_on_rotonly(label: str, model_dir: Path, gt: SfMScene) -> MethodResult:
    """Reference, not a method: pycolmap's bundle adjustment (K fixed, Ceres defaults, squared
    loss) started from rotonly's own COLMAP model (its poses, points and observations). Where
    BA moves rotonly's rotations shows how far GRRM's optimum lies from BA's on exactly the
    same tracks; the time is the bundle_adjustment call alone."""
    import pycolmap

    method = f"reference: pycolmap BA (K fixed) started from rotonly's model ({label})"
    rec = pycolmap.Reconstruction(str(model_dir))
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    previous_level = quiet_pycolmap()
    try:
        start = time.perf_counter()
        pycolmap.bundle_adjustment(rec, options)
        elapsed = time.perf_counter() - start
    finally:
        quiet_pycolmap(previous_level)
    return evaluate_scene(method, gt, reconstruction_scene(rec), elapsed, "bundle_adjustment call")


def run_global_mapper(database: Path, gt: SfMScene, threads: int, seed: int = 0) -> MethodResult:
    """pycolmap's global mapper on a copy of the database, in a child process (_mapper_worker);
    largest model. time_s is the global_mapping call (what the data README's table reports);
    extra["process_wall_s"] is the child's whole wall time, measured like ``rotonly run``."""
    import pycolmap

    method = "pycolmap global mapper (RA + GP + BA, K fixed)"
    with tempfile.TemporaryDirectory(prefix="bench_glomap_") as tmp:
        db_copy = Path(tmp) / "database.db"
        shutil.copyfile(database, db_copy)  # Database.open rewrites the header even to read
        command = mapper_worker_command(db_copy, Path(tmp) / "work", threads, seed)
        start = time.perf_counter()
        completed = subprocess.run(command, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if completed.returncode != 0:
            return MethodResult(method, num_gt=len(gt.poses), time_s=wall, time_note="process wall",
                                error=f"exit {completed.returncode}: {completed.stderr.strip().splitlines()[-1:]}")
        report = json.loads(completed.stdout.strip().splitlines()[-1])
        if not report["num_models"]:
            return MethodResult(method, num_gt=len(gt.poses), time_s=report["call_s"], error="no model")
        rec = pycolmap.Reconstruction(str(Path(tmp) / "work" / "best"))
        result = evaluate_scene(method, gt, reconstruction_scene(rec), report["call_s"], mapper_time_note(threads))
        result.extra["process_wall_s"] = wall
        result.extra["num_models"] = report["num_models"]
        result.extra["num_points"] = rec.num_points3D()
        return result


# ============================================================================ OpenMVG

#: OpenMVG's global SfM as data/strecha/README.md ran it (openmvg/global was made with -T 4)
OPENMVG_THREADS = 4
OPENMVG_TOOLS = ("openMVG_main_SfM", "openMVG_main_ConvertSfM_DataFormat")


def openmvg_global_command(openmvg_bin: Path, project: Path, out: Path, hold_intrinsics: bool = False) -> list[str]:
    """openMVG_main_SfM's global engine on ``project``'s sfm_data.json + matches.e.bin into ``out``."""
    return [str(openmvg_bin / OPENMVG_TOOLS[0]), "--sfm_engine", "GLOBAL", "-T", str(OPENMVG_THREADS),
            "--input_file", str(project / "sfm_data.json"), "--match_file", str(project / "matches.e.bin"),
            "--output_dir", str(out)] + (["-f", "NONE"] if hold_intrinsics else [])


def alternating_runs(commands: dict[str, Callable[[int], list[str]]],
                     rounds: int) -> dict[str, list[tuple[float, str]]]:
    """(process wall time in s, stdout) of every command in ``rounds`` rounds, the order
    rotated each round (round k starts with command k mod n), so that a slow stretch of the
    shared machine falls on all of them alike. ``commands[name](k)`` is the argv of round k.
    RuntimeError (with the tail of its stderr) if a command fails."""
    names = list(commands)
    runs: dict[str, list[tuple[float, str]]] = {name: [] for name in names}
    for k in range(rounds):
        for name in names[k % len(names):] + names[:k % len(names)]:
            argv = commands[name](k)
            start = time.perf_counter()
            completed = subprocess.run(argv, capture_output=True, text=True)
            runs[name].append((time.perf_counter() - start, completed.stdout))
            if completed.returncode != 0:
                tail = (completed.stderr or completed.stdout).strip().splitlines()[-1:]
                raise RuntimeError(f"{name}: exit {completed.returncode}: {tail}")
    return runs


def _round_dir(work: Path, prefix: str, k: int) -> Path:
    """``work/<prefix>_<k>`` for round k, the previous round's folder removed (a tool's output
    folder must not exist yet, and the rounds need not pile up)."""
    shutil.rmtree(work / f"{prefix}_{k - 1}", ignore_errors=True)
    return work / f"{prefix}_{k}"


def _timing_summary(rounds: int, reference: str, ours: list[float], theirs: list[float], note: str) -> dict:
    return {"rounds": rounds, "reference": reference, "reference_time": note, "rotonly_s": ours,
            "reference_s": theirs, "median_rotonly_s": float(np.median(ours)),
            "median_reference_s": float(np.median(theirs)),
            "ratio_of_medians": float(np.median(ours) / np.median(theirs))}


def openmvg_input_timing(project_dir: Path, openmvg_bin: Path, work: Path, rounds: int) -> dict:
    """``rotonly -q run`` and OpenMVG's global SfM (default settings, the issue's reference)
    on one copy of the project, ``rounds`` alternating rounds (alternating_runs): both lists
    of process wall times, their medians and the ratio of the medians. A single pair of runs
    on this shared 2-core machine moves by ±15 %, as much as the two tools differ by."""
    copy = work / "openmvg_project_timing"
    shutil.copytree(project_dir, copy, ignore=shutil.ignore_patterns("global", "eval"))

    runs = alternating_runs({
        "rotonly": lambda k: rotonly_run_command(copy / "sfm_data.json", work / "rotonly_timing"),
        "openmvg": lambda k: openmvg_global_command(openmvg_bin, copy, _round_dir(work, "openmvg_timing", k))},
        rounds)
    return _timing_summary(rounds, "OpenMVG 2.1 global SfM", [t for t, _ in runs["rotonly"]],
                           [t for t, _ in runs["openmvg"]], f"process wall, -T {OPENMVG_THREADS}")


def database_timing(database: Path, work: Path, threads: int, rounds: int, seed: int = 0) -> dict:
    """``rotonly -q run`` and pycolmap's global mapper (the _mapper_worker process) on the
    database, ``rounds`` alternating rounds: rotonly's process wall times against the
    mapper's global_mapping call (the data README's measure, as in the single-run ratio) and
    against the mapper's whole process."""
    def mapper_run(k: int) -> list[str]:
        folder = _round_dir(work, "mapper_timing", k)
        folder.mkdir()
        shutil.copyfile(database, folder / "database.db")  # Database.open rewrites the header
        return mapper_worker_command(folder / "database.db", folder / "work", threads, seed)

    runs = alternating_runs({
        "rotonly": lambda k: rotonly_run_command(database, work / "rotonly_db_timing"),
        "mapper": mapper_run}, rounds)
    ours = [t for t, _ in runs["rotonly"]]
    calls = [json.loads(out.strip().splitlines()[-1])["call_s"] for _, out in runs["mapper"]]
    summary = _timing_summary(rounds, "pycolmap global mapper", ours, calls, mapper_time_note(threads))
    walls = [t for t, _ in runs["mapper"]]
    summary.update(reference_process_s=walls, ratio_to_process_medians=float(np.median(ours) / np.median(walls)))
    return summary


def run_openmvg_global(project_dir: Path, gt: SfMScene, openmvg_bin: Path, work: Path, log_dir: Path,
                       hold_intrinsics: bool = False) -> MethodResult:
    """OpenMVG 2.1's own global SfM (L2 rotation averaging + LiGT + BA) re-run on a copy of the
    project's matches, timed like ``rotonly run``: the whole process's wall time. OpenMVG's own
    "Total Sfm took (s)" line (whole seconds, without start-up and loading) goes to extra.
    The result is converted to sfm_data.json by OpenMVG's ConvertSfM_DataFormat (not timed).

    By default its BA refines the intrinsics (OpenMVG's default, as the stored result was
    made); ``hold_intrinsics`` passes ``-f NONE``, the K-fixed setting rotonly and the
    pycolmap mapper run in."""
    import re

    variant = "_held_k" if hold_intrinsics else ""
    method = ("OpenMVG 2.1 global SfM (LiGT + BA, intrinsics held: -f NONE, re-run here)" if hold_intrinsics
              else "OpenMVG 2.1 global SfM (LiGT + BA, re-run here)")
    copy = work / f"openmvg_project{variant}"
    shutil.copytree(project_dir, copy, ignore=shutil.ignore_patterns("global", "eval"))
    out = work / f"openmvg_global{variant}"
    command = openmvg_global_command(openmvg_bin, copy, out, hold_intrinsics)
    start = time.perf_counter()
    completed = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    convert = [str(openmvg_bin / OPENMVG_TOOLS[1]), "-i", str(out / "sfm_data.bin"), "-o",
               str(out / "sfm_data.json"), "-V", "-I", "-E"]
    log = f"$ {' '.join(command)}\nexit {completed.returncode}\n--- stdout\n{completed.stdout}--- stderr\n" \
          f"{completed.stderr}"
    failed = completed if completed.returncode != 0 else None
    if failed is None:
        converted = subprocess.run(convert, capture_output=True, text=True)
        log += f"$ {' '.join(convert)}\nexit {converted.returncode}\n{converted.stderr}"
        failed = converted if converted.returncode != 0 else None
    (log_dir / f"openmvg_global{variant}_{project_dir.parent.name}.log").write_text(log)
    if failed is not None:
        tail = (failed.stderr or failed.stdout).strip().splitlines()[-1:]
        return MethodResult(method, num_gt=len(gt.poses), time_s=wall, time_note="subprocess wall",
                            error=f"exit {failed.returncode}: {tail}")
    result = evaluate_scene(method, gt, openmvg.read_sfm_data(out / "sfm_data.json"), wall,
                            f"subprocess wall, -T {OPENMVG_THREADS}")
    own = re.search(r"Total Sfm took \(s\):\s*([0-9.]+)", completed.stdout + completed.stderr)
    result.extra["openmvg_reported_s"] = float(own.group(1)) if own else None
    return result


def check_openmvg_bin(openmvg_bin: Path) -> str | None:
    """Why ``openmvg_bin`` cannot be used, or None."""
    missing = [t for t in OPENMVG_TOOLS if not os.access(openmvg_bin / t, os.X_OK)]
    return f"{openmvg_bin} lacks {', '.join(missing)}" if missing else None


# ============================================================================ one scene

def bench_scene(scene_dir: Path, work: Path, log_dir: Path, threads: int, skip_mapper: bool,
                openmvg_bin: Path | None = None, timing_rounds: int = 1) -> list[MethodResult]:
    name = scene_dir.name
    gt = detect.read_ground_truth(scene_dir)
    database = scene_dir / "database.db"
    project = scene_dir / "openmvg" / "sfm_data.json"
    results: list[MethodResult] = []

    def guarded(method: str, fn, *args):
        try:
            out = fn(*args)
            results.extend(out if isinstance(out, list) else [out])
        except Exception as exc:  # a failing method is a table row, not a crashed benchmark
            results.append(MethodResult(method, num_gt=len(gt.poses), error=f"{type(exc).__name__}: {exc}"))
        print(f"  [{name}] {method}: done", file=sys.stderr, flush=True)

    def attach_timing(method: str, fn, *args):
        # --timing-rounds: the alternating timing goes with the rotonly row it refines
        ours = next((r for r in results if r.method == method and not r.error), None)
        if timing_rounds < 2 or ours is None:
            return
        try:
            ours.extra["alternating_timing"] = fn(*args)
        except Exception as exc:  # a failed timing is a note in the table, not a crashed benchmark
            ours.extra["alternating_timing"] = {"error": f"{type(exc).__name__}: {exc}"}
        print(f"  [{name}] alternating wall times ({method}): done", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix=f"bench_{name}_", dir=work) as tmp:
        tmp = Path(tmp)
        if database.is_file():
            guarded("rotonly run database.db", run_rotonly_subprocess, "rotonly run database.db", database, gt,
                    tmp, log_dir)
        if project.is_file():
            guarded("rotonly run openmvg/sfm_data.json", run_rotonly_subprocess,
                    "rotonly run openmvg/sfm_data.json", project, gt, tmp, log_dir)
        if database.is_file():
            guarded("rotonly stages (database.db)", lambda: run_rotonly_stages("database.db", database, gt)[0])
        if project.is_file():
            guarded("rotonly stages (openmvg)", lambda: run_rotonly_stages("openmvg", project, gt)[0])
        if database.is_file():
            guarded("pycolmap RA on stored geometries", run_pycolmap_stored, database, gt)
            if not skip_mapper:
                guarded("pycolmap global mapper", run_global_mapper, database, gt, threads)
                attach_timing("rotonly run database.db", database_timing, database, tmp, threads, timing_rounds)
        if openmvg_bin is not None and (project.parent / "matches.e.bin").is_file():
            guarded("OpenMVG 2.1 global SfM (re-run)", run_openmvg_global, project.parent, gt, openmvg_bin, tmp,
                    log_dir)
            guarded("OpenMVG 2.1 global SfM (re-run, intrinsics held)", run_openmvg_global, project.parent, gt,
                    openmvg_bin, tmp, log_dir, True)
            attach_timing("rotonly run openmvg/sfm_data.json", openmvg_input_timing, project.parent, openmvg_bin,
                          tmp, timing_rounds)
        for label, method in (("database.db", "rotonly run database.db"),
                              ("openmvg", "rotonly run openmvg/sfm_data.json")):
            model = rotonly_out_dir(tmp, method) / "sparse"
            if model.is_dir():
                guarded(f"pycolmap BA from rotonly's model ({label})", run_ba_on_rotonly, label, model, gt)
    global_sfm = scene_dir / "openmvg" / "global" / "sfm_data.json"
    if global_sfm.is_file():
        guarded("OpenMVG 2.1 global SfM", lambda: evaluate_scene(
            "OpenMVG 2.1 global SfM (LiGT + BA, stored result)", gt, openmvg.read_sfm_data(global_sfm),
            OPENMVG_GLOBAL_TIME_S.get(name), "README, not re-run"))
    return results


# ============================================================================ tables

def fmt(value: float | None, digits: int = 4) -> str:
    if value is None or not np.isfinite(value):
        return "–"
    return f"{value:.{digits}f}"


def scene_table(name: str, results: list[MethodResult]) -> str:
    lines = [f"### {name}", "",
             "| method | rot. error mean (deg) | median (deg) | position error mean (GT units) | registered "
             "| time (s) | time measured as |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        if r.error:
            lines.append(f"| {r.method} | failed: {r.error} | | | | {fmt(r.time_s, 2)} | {r.time_note} |")
            continue
        lines.append(f"| {r.method} | {fmt(r.rotation_mean_deg)} | {fmt(r.rotation_median_deg)} | "
                     f"{fmt(r.position_mean)} | {r.num_registered}/{r.num_gt} | {fmt(r.time_s, 2)} | {r.time_note} |")
    lines += ratio_lines(results)
    stage_rows = [r for r in results if "stage_times_s" in r.extra and r.method.startswith("rotonly run")]
    if stage_rows:
        lines += ["", f"rotonly internal stage times (s, OUT/reports/<stage>.json), {name}:", "",
                  "| input | " + " | ".join(STAGE_NAMES) + " | run total | subprocess wall | subprocess CPU |",
                  "|---|" + "---|" * (len(STAGE_NAMES) + 3)]
        for r in stage_rows:
            times = r.extra["stage_times_s"]
            lines.append(f"| {r.method.removeprefix('rotonly run ')} | "
                         + " | ".join(fmt(times.get(s), 2) for s in STAGE_NAMES)
                         + f" | {fmt(times.get('run'), 2)} | {fmt(r.time_s, 2)} "
                         f"| {fmt(r.extra.get('subprocess_cpu_s'), 2)} |")
    return "\n".join(lines)


def ratio_lines(results: list[MethodResult]) -> list[str]:
    """rotonly's wall time over each reference's, the reference timed both as its call and as a
    whole process (the way rotonly is timed)."""
    by_method = {r.method: r for r in results if not r.error and r.time_s}
    pairs = [("rotonly run database.db", "pycolmap global mapper (RA + GP + BA, K fixed)"),
             ("rotonly run openmvg/sfm_data.json", "OpenMVG 2.1 global SfM (LiGT + BA, re-run here)")]
    out = []
    for ours, theirs in pairs:
        if ours in by_method and theirs in by_method:
            mine, ref = by_method[ours], by_method[theirs]
            text = f"{ours} / {theirs.split(' (')[0]}: {mine.time_s / ref.time_s:.2f}x ({ref.time_note})"
            if ref.extra.get("process_wall_s"):
                text += f", {mine.time_s / ref.extra['process_wall_s']:.2f}x of its process wall " \
                        f"({ref.extra['process_wall_s']:.2f} s)"
            out.append(f"- time ratio {text}")
    for ours, _ in pairs:
        timing = by_method.get(ours, MethodResult("")).extra.get("alternating_timing")
        if timing and "error" in timing:
            out.append(f"- alternating wall times of {ours} failed: {timing['error']}")
        elif timing:
            ratios = np.array(timing["rotonly_s"]) / np.array(timing["reference_s"])
            text = (f"- {timing['rounds']} alternating rounds, {ours} / {timing['reference']} "
                    f"({timing['reference_time']}, medians): {timing['median_rotonly_s']:.2f} / "
                    f"{timing['median_reference_s']:.2f} s = "
                    f"**{timing['ratio_of_medians']:.2f}x** (per round {ratios.min():.2f}-{ratios.max():.2f}x)")
            if "ratio_to_process_medians" in timing:
                text += f"; {timing['ratio_to_process_medians']:.2f}x of its process wall"
            out.append(text)
    return [""] + out if out else []


def summary_table(all_results: dict[str, list[MethodResult]]) -> str:
    scenes = list(all_results)
    methods: list[str] = []
    for results in all_results.values():
        for r in results:
            if r.method not in methods:
                methods.append(r.method)
    lines = ["### Summary: mean rotation error in degrees (time in s)", "",
             "| method | " + " | ".join(scenes) + " |", "|---|" + "---|" * len(scenes)]
    for method in methods:
        cells = []
        for scene in scenes:
            r = next((x for x in all_results[scene] if x.method == method), None)
            if r is None:
                cells.append("")
            elif r.error:
                cells.append("failed")
            else:
                missing = "" if r.num_registered == r.num_gt else f", {r.num_registered}/{r.num_gt} reg."
                cells.append(f"{fmt(r.rotation_mean_deg)} ({fmt(r.time_s, 1)} s{missing})")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--mapper-worker"]:
        return _mapper_worker(*argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="folder of Strecha scene folders")
    parser.add_argument("--scenes", nargs="*", default=None, help="scene folder names (default: all)")
    parser.add_argument("-o", "--output", type=Path, default=Path("bench_results/strecha"),
                        help="results folder (replaced atomically)")
    parser.add_argument("--threads", type=int, default=-1, help="pycolmap global mapper threads (-1: all)")
    parser.add_argument("--skip-mapper", action="store_true", help="leave out the pycolmap global mapper")
    parser.add_argument("--openmvg-bin", type=Path, default=None,
                        help="folder of OpenMVG 2.1's tools (openMVG_main_SfM, ..._ConvertSfM_DataFormat): also "
                             "re-run OpenMVG's global SfM on each scene's openmvg/ matches and time it like rotonly")
    parser.add_argument("--timing-rounds", type=int, default=1,
                        help="also time rotonly against the mapper on each database and (with --openmvg-bin) against "
                             "OpenMVG on each scene's OpenMVG matches in this many alternating rounds, and report "
                             "the medians (default 1: the single runs only)")
    parser.add_argument("--results-md", type=Path, default=None,
                        help="also write the tables into this file's `strecha-tools` section (docs/results.md)")
    args = parser.parse_args(argv)
    if args.timing_rounds < 1:
        parser.error("--timing-rounds: must be >= 1")

    root = args.root.resolve()
    results_dir = args.output.resolve()
    if results_dir.is_relative_to(root):
        parser.error("the results folder must not lie inside ROOT (inputs are never modified)")
    scene_dirs = sorted(p for p in root.iterdir() if p.is_dir() and (p / detect.GT_SUBDIR).is_dir())
    if args.scenes:
        scene_dirs = [p for p in scene_dirs if p.name in args.scenes]
        unknown = set(args.scenes) - {p.name for p in scene_dirs}
        if unknown:
            parser.error(f"unknown scenes: {', '.join(sorted(unknown))}")
    if not scene_dirs:
        parser.error(f"no scene folder with {detect.GT_SUBDIR}/ under {root}")
    openmvg_bin = args.openmvg_bin.resolve() if args.openmvg_bin is not None else None
    if openmvg_bin is not None and check_openmvg_bin(openmvg_bin):
        parser.error(f"--openmvg-bin: {check_openmvg_bin(openmvg_bin)}")

    results_dir.parent.mkdir(parents=True, exist_ok=True)
    # subprocess logs and rotonly workspaces live beside RESULTS_DIR until the end
    log_dir = Path(tempfile.mkdtemp(prefix=f".{results_dir.name}.logs.", dir=results_dir.parent))
    all_results: dict[str, list[MethodResult]] = {}
    byte_compile_rotonly()
    load_at_start = os.getloadavg()[0]  # other processes on the 2 cores inflate every time here
    previous_log_level = quiet_pycolmap()
    start = time.perf_counter()
    try:
        for scene_dir in scene_dirs:
            print(f"== {scene_dir.name}", file=sys.stderr, flush=True)
            all_results[scene_dir.name] = bench_scene(scene_dir, results_dir.parent, log_dir, args.threads,
                                                      args.skip_mapper, openmvg_bin, args.timing_rounds)
            print(scene_table(scene_dir.name, all_results[scene_dir.name]) + "\n", flush=True)
        summary = summary_table(all_results) + (
            f"\n\nLoad average (1 min) at start / end: {load_at_start:.1f} / {os.getloadavg()[0]:.1f} "
            f"on {os.cpu_count()} cores; code {code_version()}.")
        print(summary)
        table = "\n\n".join([scene_table(n, r) for n, r in all_results.items()] + [summary])
        payload = {"root": str(root), "command": " ".join([Path(sys.argv[0]).name] + (argv or sys.argv[1:])),
                   "rotonly": " ".join(rotonly_command()), "code_version": code_version(),
                   "cpu_count": os.cpu_count(),
                   "load_average_1min_start_end": [load_at_start, os.getloadavg()[0]],
                   "total_time_s": time.perf_counter() - start,
                   "scenes": {n: [vars(r) for r in rs] for n, rs in all_results.items()}}
        write_results(results_dir, payload, table, log_dir)
        results_md.record(args.results_md, "strecha-tools", "Strecha: rotonly against pycolmap's global mapper "
                          "and OpenMVG", results_md.command_line("python scripts/bench/strecha_tools.py", argv),
                          "\n\n".join([summary] + [scene_table(n, r) for n, r in all_results.items()]))
    finally:
        shutil.rmtree(log_dir, ignore_errors=True)
        quiet_pycolmap(previous_log_level)
    print(f"\nwrote {results_dir}/results.json and table.md ({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    return 0


def write_results(results_dir: Path, payload: dict, table: str, log_dir: Path) -> None:
    """results.json, table.md and logs/ (subprocess output) into a temporary sibling of RESULTS_DIR,
    renamed over it at the end (no partial results)."""
    from rotonly_cli.io.atomic import staging_dir

    results_dir.parent.mkdir(parents=True, exist_ok=True)
    with staging_dir(results_dir) as tmp:
        (tmp / "results.json").write_text(json.dumps(payload, indent=1, default=float) + "\n")
        (tmp / "table.md").write_text(table + "\n")
        if log_dir.is_dir():
            shutil.copytree(log_dir, tmp / "logs")


if __name__ == "__main__":
    sys.exit(main())
