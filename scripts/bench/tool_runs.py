"""How the benchmarks run and score the tools (strecha_tools.py, scale.py, guessed_focal.py and the
research probes use it): one evaluator for every estimate (``MethodResult``), ``rotonly run`` as
its users start it, pycolmap's rotation averaging, global mapper (a child process: this file
run with ``--mapper-worker``) and bundle adjustment, OpenMVG's global SfM, and alternating
timed rounds."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.evaluation.quality import evaluate
from rotonly_cli.io import openmvg
from rotonly_cli.scene.types import Pose, SfMScene, View


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

    from rotonly_cli.baselines.references import global_mapper_options

    pycolmap.logging.minloglevel = 2
    options = global_mapper_options(pycolmap, int(seed), int(threads))
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


if __name__ == "__main__":
    if sys.argv[1:2] != ["--mapper-worker"]:
        sys.exit("usage: tool_runs.py --mapper-worker DATABASE OUT THREADS SEED")
    sys.exit(_mapper_worker(*sys.argv[2:]))
