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
from pathlib import Path

import numpy as np

from rotonly_cli.bench import results_md
from rotonly_cli.bench.common import code_version
from rotonly_cli.io import detect, openmvg
from rotonly_cli.scene.types import SfMScene

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tool_runs import (  # noqa: E402
    MethodResult,
    byte_compile_rotonly,
    check_openmvg_bin,
    database_timing,
    evaluate_scene,
    openmvg_input_timing,
    pycolmap_ra_results,
    quiet_pycolmap,
    rotations_scene,
    rotonly_command,
    rotonly_run_command,
    run_ba_on_rotonly,
    run_global_mapper,
    run_openmvg_global,
    run_pycolmap_stored,
)

#: OpenMVG 2.1 global SfM wall time on this machine type (data/strecha/README.md, "What the
#: references reach"); the stored result is evaluated, the tool is not re-run.
OPENMVG_GLOBAL_TIME_S = {"fountain-P11": 5.0, "Herz-Jesus-P8": 1.0, "entry-P10": 2.0}
STAGE_NAMES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


# ============================================================================ rotonly

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
