"""Issue-5 scale benchmark: time and peak memory of every rotonly stage on synthetic scenes.

Usage: python scripts/bench/scale.py [--sizes 100 300 1000] [--points-per-view 100] [--setup linear]
                                     [--window 5] [--max-height 100] [--cache DIR] [-o RESULTS_DIR]

Per size n: ``simulate_multiview(setup, num_views=n, num_points=points_per_view * n,
init="perturbed")`` (GT relative rotations perturbed by 0.5°, so no 5-point RANSAC is spent
on the simulation and the load stage keeps the stored CALIBRATED poses), written as a COLMAP
database (+ ``gt.npz``) in a subprocess; the files are cached under ``--cache``. Then a
fresh subprocess per size runs the pipeline stages in-process on that database, as
``rotonly run`` does (load / identify / refine / average / optimize = GRRM / translate /
triangulate / export; in the console script's process settings, runtime/startup.py), and
measures per stage:

* wall time (``time.perf_counter``);
* the process's peak resident memory during the stage: the kernel's high-water mark
  ``VmHWM`` (``/proc/self/status``), reset before each stage by writing 5 to
  ``/proc/self/clear_refs`` (Linux ≥ 4.0), so it covers numpy and C++ (pycolmap) buffers and
  includes everything the process already holds (the scene, the view graph). Where the reset
  is not allowed the column is the running maximum (``ru_maxrss``) and says so.

The issue's target: GRRM on the 1000-camera, 100 000-point scene in ≤ 60 s and ≤ 4 GB on 2 cores.
The rotation errors (geodesic after the global rotation alignment, evaluation.quality) of the
averaged rotations (GRRM start) and of GRRM are printed as a sanity check.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rotonly_cli.runtime import startup

# the process `rotonly run` runs in (cli.console_main): one BLAS thread, freed heap kept;
# before numpy is imported
startup.rotonly_process_settings()

import numpy as np  # noqa: E402

from rotonly_cli.bench import results_md  # noqa: E402
from rotonly_cli.bench.common import code_version  # noqa: E402
from rotonly_cli.io.atomic import staging_dir  # noqa: E402

STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate", "export")
STAGE_TITLES = {"optimize": "GRRM"}
GRRM_TARGET_S = 60.0
GRRM_TARGET_GB = 4.0


# ============================================================================ memory probes

def _status_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss() -> bool:
    """Reset the kernel's resident high-water mark (VmHWM); False where not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb(resettable: bool) -> float:
    """Peak resident memory since the last reset (VmHWM), else since the process started."""
    hwm = _status_kb("VmHWM") if resettable else None
    if hwm is None:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return hwm / 1024.0


# ============================================================================ subprocess: simulate

def simulate_to(out_dir: Path, num_views: int, num_points: int, setup: str, window: int, max_height: float,
                seed: int) -> None:
    """Simulated scene -> out_dir/{database.db, gt.npz, simulation.json}, atomically."""
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    start = time.perf_counter()
    problem = simulate_multiview(setup, num_views=num_views, num_points=num_points, window=window,
                                 max_height=max_height, init="perturbed", rng=seed)
    simulate_s = time.perf_counter() - start
    with staging_dir(out_dir) as tmp:
        start = time.perf_counter()
        write_database(tmp / "database.db", problem.scene)
        write_s = time.perf_counter() - start
        view_ids = sorted(problem.gt_poses)
        np.savez(tmp / "gt.npz", names=np.array([problem.scene.views[v].name for v in view_ids]),
                 R_cam_from_world=np.stack([problem.gt_poses[v].R_cam_from_world for v in view_ids]),
                 centers=np.stack([problem.gt_poses[v].center for v in view_ids]))
        track_lengths = problem.visibility.sum(axis=0)
        info = {"setup": setup, "num_views": num_views, "num_points": num_points, "window": window,
                "max_height": max_height, "seed": seed, "init": "perturbed",
                "num_pairs": len(problem.scene.pairs),
                "num_matches": int(sum(len(p.matches) for p in problem.scene.pairs.values())),
                "num_observations": int(track_lengths.sum()), "track_length_mean": float(track_lengths.mean()),
                "simulate_s": simulate_s, "write_database_s": write_s,
                "simulate_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
        (tmp / "simulation.json").write_text(json.dumps(info, indent=1) + "\n")


# ============================================================================ subprocess: measure

def rotation_errors(names: list[str], R_est: np.ndarray, gt: dict) -> dict:
    """Mean / median rotation error (deg) of the registered rows against gt.npz (evaluation.quality)."""
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.scene.types import Pose, SfMScene, View

    gt_names = [str(n) for n in gt["names"]]
    gt_scene, estimate = SfMScene(source="simulation-gt"), SfMScene(source="bench")
    for k, name in enumerate(gt_names):
        gt_scene.views[k] = View(k, name, 0)
        gt_scene.poses[k] = Pose(gt["R_cam_from_world"][k], gt["centers"][k])
    for k, name in enumerate(names):
        if np.all(np.isfinite(R_est[k])):
            estimate.views[k] = View(k, name, 0)
            estimate.poses[k] = Pose(R_est[k], np.zeros(3))  # rotation-only: no position metric
    report = evaluate(gt_scene, estimate)
    return {"mean": report.rotation_error_deg.mean, "median": report.rotation_error_deg.median,
            "max": report.rotation_error_deg.max, "registered": report.num_matched}


def _children_cpu_s() -> float:
    """User + system CPU of this process's finished children (forked TRRM parts, GRRM's and LiGT's helpers,
    the sfm_data.json writer), so that a stage's CPU includes the work it forked out."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def measure(scene_dir: Path, out_json: Path, jobs: int = 1) -> None:
    """Run the stages on scene_dir/database.db in this process; per-stage time and peak RSS.
    ``jobs``: processes (RunOptions.jobs, `rotonly run --jobs`)."""
    from rotonly_cli.pipeline import STAGE_FUNCTIONS, RunOptions, load_stage, write_outputs

    resettable = reset_peak_rss()
    rows: dict[str, dict] = {}
    run = None
    averaged = None
    total_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_scale_export_") as export_dir:
        for stage in STAGES:
            reset_peak_rss()
            cpu_start = time.process_time() + _children_cpu_s()
            start = time.perf_counter()
            if stage == "load":
                run = load_stage(scene_dir / "database.db", RunOptions(jobs=jobs))
            elif stage == "export":
                write_outputs(Path(export_dir), run)[1].result()
            else:
                STAGE_FUNCTIONS[stage](run)
            elapsed = time.perf_counter() - start
            rows[stage] = {"time_s": elapsed, "cpu_s": time.process_time() + _children_cpu_s() - cpu_start,
                           "peak_rss_mb": peak_rss_mb(resettable),
                           "rss_after_mb": (_status_kb("VmRSS") or 0) / 1024.0}
            if stage == "average":
                averaged = run.rotations.copy()
            print(f"  {stage}: {elapsed:.2f} s (CPU {rows[stage]['cpu_s']:.2f} s), "
                  f"peak RSS {rows[stage]['peak_rss_mb']:.0f} MB", file=sys.stderr,
                  flush=True)
    total = time.perf_counter() - total_start
    gt = dict(np.load(scene_dir / "gt.npz"))
    names = [run.graph.views[v].name for v in run.graph.view_ids()]
    optimize_report = run.reports.get("optimize", {})
    result = {
        "stages": rows, "total_s": total, "peak_rss_resettable": resettable,
        "process_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        # the largest forked child's peak RSS, its pages shared with this process included
        "children_peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
        "num_active_edges": len(run.graph.active_edges()),
        "num_points_triangulated": 0 if run.structure is None else len(run.structure.points),
        "grrm": {k: optimize_report.get(k) for k in ("num_views", "num_edges", "num_matches", "iterations",
                                                     "converged", "cost_before", "cost_after")},
        "rotation_error_averaged_deg": rotation_errors(names, averaged, gt),
        "rotation_error_grrm_deg": rotation_errors(names, run.rotations, gt),
    }
    out_json.write_text(json.dumps(result, indent=1, default=float) + "\n")


# ============================================================================ parent



def run_child(args: list[str], timeout: float) -> tuple[float, subprocess.CompletedProcess]:
    start = time.perf_counter()
    completed = subprocess.run([sys.executable, str(Path(__file__).resolve())] + args, stdout=subprocess.PIPE,
                               stderr=None, text=True, timeout=timeout)
    return time.perf_counter() - start, completed


def fmt(value, digits: int = 2) -> str:
    return "–" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def tables(results: list[dict]) -> str:
    head = ["cameras", "points", "pairs", "matches"] + [STAGE_TITLES.get(s, s) for s in STAGES] + ["total"]
    time_lines = ["### Stage wall time (s); CPU time (all threads) in results.json", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    memory_lines = ["### Peak resident memory of the process during each stage (MB)", "",
                    "| " + " | ".join(head[:4] + [STAGE_TITLES.get(s, s) for s in STAGES] + ["max"]) + " |",
                    "|" + "---|" * len(head)]
    accuracy_lines = ["### Rotation error (deg, mean / median) and GRRM", "",
                      "| cameras | averaged (GRRM start) | GRRM | GRRM iterations | GRRM wall (s) | GRRM CPU (s) "
                      "| GRRM peak RSS (GB) | target ≤ 60 s, ≤ 4 GB |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        sim, m = r["simulation"], r.get("measure")
        first = [str(sim["num_views"]), str(sim["num_points"]), str(sim["num_pairs"]), str(sim["num_matches"])]
        if m is None:
            time_lines.append("| " + " | ".join(first + [f"failed: {r.get('error', '')}"] + [""] * len(STAGES)) + " |")
            continue
        stages = m["stages"]
        time_lines.append("| " + " | ".join(first + [fmt(stages[s]["time_s"]) for s in STAGES]
                                            + [fmt(m["total_s"])]) + " |")
        peaks = [stages[s]["peak_rss_mb"] for s in STAGES]
        memory_lines.append("| " + " | ".join(first + [fmt(p, 0) for p in peaks] + [fmt(max(peaks), 0)]) + " |")
        a, g = m["rotation_error_averaged_deg"], m["rotation_error_grrm_deg"]
        grrm_s, grrm_gb = stages["optimize"]["time_s"], stages["optimize"]["peak_rss_mb"] / 1024.0
        met = "met" if grrm_s <= GRRM_TARGET_S and grrm_gb <= GRRM_TARGET_GB else "NOT met"
        accuracy_lines.append(f"| {sim['num_views']} | {fmt(a['mean'], 4)} / {fmt(a['median'], 4)} | "
                              f"{fmt(g['mean'], 4)} / {fmt(g['median'], 4)} | {m['grrm'].get('iterations')} | "
                              f"{fmt(grrm_s)} | {fmt(stages['optimize'].get('cpu_s'))} | {fmt(grrm_gb, 2)} | {met} |")
    note = ("Peak memory: VmHWM reset before each stage (/proc/self/clear_refs); it includes what the process "
            "already holds." if all(r.get("measure", {}).get("peak_rss_resettable", True) for r in results)
            else "Peak memory: running maximum ru_maxrss (VmHWM could not be reset here).")
    note += (" Forked children (TRRM's parts, GRRM's and LiGT's helpers, the sfm_data.json writer) are not in it: they "
             "share the process's pages until they write them (the largest child's peak RSS, shared pages "
             "counted, is children_peak_rss_mb in results.json); the CPU times include them.")
    return "\n".join(time_lines + [""] + memory_lines + ["", note, ""] + accuracy_lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000], help="numbers of cameras")
    parser.add_argument("--points-per-view", type=int, default=100, help="points = this × cameras")
    parser.add_argument("--setup", default="linear", choices=("circular", "square", "linear", "outward"))
    parser.add_argument("--window", type=int, default=5, help="pairs: cameras at most this far apart")
    parser.add_argument("--max-height", type=float, default=100.0,
                        help="points up to this height (m): shorter tracks (mean ~7 views at 100 m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "rotonly_bench_scale_cache",
                        help="simulated databases are kept here and reused")
    parser.add_argument("-o", "--output", type=Path, default=Path("bench_results/scale"))
    parser.add_argument("--timeout", type=float, default=3600.0, help="per child process (s)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="processes, as `rotonly run --jobs` (default: the usable CPUs, as rotonly run)")
    parser.add_argument("--results-md", type=Path, default=None,
                        help="also write the tables into this file's `scale` section (docs/results.md)")
    parser.add_argument("--_simulate", nargs=2, metavar=("VIEWS", "DIR"), help=argparse.SUPPRESS)
    parser.add_argument("--_measure", nargs=2, metavar=("DIR", "JSON"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args._simulate:
        views = int(args._simulate[0])
        simulate_to(Path(args._simulate[1]), views, args.points_per_view * views, args.setup, args.window,
                    args.max_height, args.seed)
        return 0
    if args._measure:
        measure(Path(args._measure[0]), Path(args._measure[1]), args.jobs or 1)
        return 0

    from rotonly_cli.runtime.parallel import usable_cpus

    jobs = usable_cpus() if args.jobs is None else args.jobs
    results = []
    load_at_start = os.getloadavg()[0]  # other processes on the 2 cores inflate every time here
    common = ["--points-per-view", str(args.points_per_view), "--setup", args.setup, "--window", str(args.window),
              "--max-height", str(args.max_height), "--seed", str(args.seed)]
    for views in args.sizes:
        key = (f"{args.setup}_v{views}_p{args.points_per_view * views}_w{args.window}_h{args.max_height:g}"
               f"_s{args.seed}")
        scene_dir = args.cache / key
        if not (scene_dir / "simulation.json").is_file():
            print(f"== simulating {views} cameras -> {scene_dir}", file=sys.stderr, flush=True)
            elapsed, completed = run_child(common + ["--_simulate", str(views), str(scene_dir)], args.timeout)
            if completed.returncode != 0:
                print(f"simulation of {views} cameras failed (exit {completed.returncode})", file=sys.stderr)
                return 1
        simulation = json.loads((scene_dir / "simulation.json").read_text())
        print(f"== {views} cameras: {simulation['num_points']} points, {simulation['num_pairs']} pairs, "
              f"{simulation['num_matches']} matches", file=sys.stderr, flush=True)
        entry = {"simulation": simulation, "scene_dir": str(scene_dir)}
        with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
            out_json = Path(tmp) / "measure.json"
            try:
                elapsed, completed = run_child(["--jobs", str(jobs), "--_measure", str(scene_dir), str(out_json)],
                                               args.timeout)
                entry["child_wall_s"] = elapsed
                if completed.returncode == 0:
                    entry["measure"] = json.loads(out_json.read_text())
                else:
                    entry["error"] = f"exit {completed.returncode}"
            except subprocess.TimeoutExpired:
                entry["error"] = f"timeout {args.timeout:.0f} s"
        results.append(entry)

    table = tables(results) + (f"\n\nLoad average (1 min) at start / end: {load_at_start:.1f} / "
                               f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; TRRM jobs={jobs}; "
                               f"code {code_version()}.")
    print(table)
    payload = {"command": " ".join(["scale.py"] + (argv if argv is not None else sys.argv[1:])),
               "code_version": code_version(), "cpu_count": os.cpu_count(),
               "load_average_1min_start_end": [load_at_start, os.getloadavg()[0]],
               "results": results}
    out_dir = args.output.resolve()
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    with staging_dir(out_dir) as tmp:
        (tmp / "results.json").write_text(json.dumps(payload, indent=1, default=float) + "\n")
        (tmp / "table.md").write_text(table + "\n")
    results_md.record(args.results_md, "scale", "Scale: every stage on large simulated scenes",
                      results_md.command_line("python scripts/bench/scale.py", argv), table)
    print(f"\nwrote {out_dir}/results.json and table.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
