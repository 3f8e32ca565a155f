"""Scale benchmark (issue 49): the whole `rotonly run` against pycolmap's global mapper on large
simulated collections, each a process, side by side on the same database.

Usage: python scripts/bench/scale.py [--recipes circular-200 circular-1000 ...] [--rounds 1]
                                     [--cache DIR] [-o RESULTS_DIR] [--no-mapper] [--jobs 2]
                                     [--results-md docs/results.md] [--section scale] [--mapper-only]
                                     [--consensus auto|full|fast]

Per recipe (``RECIPES``: `rotonly simulate multiview ... --format colmap` arguments), the input is
made once (cached under ``--cache``), then in ``--rounds`` rounds, the order alternating:
* `rotonly -q run DATABASE -o OUT --jobs J [--consensus C]` as a process, with ROTONLY_STAGE_PEAKS=1:
  wall time, the per-stage time and peak RSS it recorded itself (OUT/reports/resources.json)
  and the process's peak RSS (the largest of those and of the kernel's accounting of the
  finished child, os.wait4, which then covers what follows the last stage), registered views, points, mean
  rotation error and position error (OUT/reports/run.json and eval/);
* pycolmap's global mapper (GLOMAP, intrinsics fixed; scripts/bench/tool_runs.py's worker
  process) on a private copy of the database: wall time, peak RSS, registered views, points and
  the same evaluation (evaluation.quality) of its largest model.
Bytes per match = peak RSS / the input's inlier matches (the verified matches in the database).
A run that fails or is killed is a row with its exit status, not an abort.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import tool_runs  # noqa: E402

from rotonly_cli.bench import results_md  # noqa: E402
from rotonly_cli.io import detect  # noqa: E402

#: name -> `rotonly simulate multiview` arguments (COLMAP databases; noise 1 px, f 800 px)
RECIPES = {
    "circular-200": "--setup circular --views 200 --points 20000 --window 10 --seed 1",
    "circular-1000": ("--setup circular --views 1000 --points 100000 --window 10 --seed 1 --corrupt-fraction 0.05 "
                      "--epipolar-outlier-fraction 0.05"),
    "circular-3000": ("--setup circular --views 3000 --points 300000 --window 10 --seed 1 --corrupt-fraction 0.05 "
                      "--epipolar-outlier-fraction 0.05"),
    # every pair matched (1225), 6.1 M matches, tracks of ~31 of the 50 views, 10 % wrong matches
    "all-50": "--setup circular --views 50 --points 13400 --window 25 --seed 1 --epipolar-outlier-fraction 0.1",
    # --window 4: 39 990 pairs (--window 3 makes 3n - 6 = 29 994), ~29 M matches
    "linear-10000": "--setup linear --views 10000 --points 300000 --window 4 --seed 1",
}
STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


def timed_process(argv: list[str], log: Path, timeout: float | None = None, env: dict | None = None) -> dict:
    """Run ``argv`` (stdout and stderr to ``log``; killed after ``timeout`` s): wall time, exit
    status and the child's peak RSS from the kernel's accounting of it (os.wait4's ru_maxrss, KB
    on Linux: the process alone, not its forked helpers)."""
    with open(log, "w") as out:
        start = time.perf_counter()
        process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env)
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            pid, status, usage = os.wait4(process.pid, 0 if deadline is None else os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                process.kill()
                deadline = None
            time.sleep(0.2)
        wall = time.perf_counter() - start
    process.returncode = os.waitstatus_to_exitcode(status)
    return {"wall_s": wall, "exit": process.returncode, "peak_rss_mb": usage.ru_maxrss / 1024.0}


def make_input(name: str, cache: Path) -> Path:
    """The recipe's simulated folder (database.db, gt/), made once."""
    folder = cache / name
    if (folder / "simulation.json").is_file():
        return folder
    if folder.exists():
        shutil.rmtree(folder)
    argv = tool_runs.rotonly_command() + ["-q", "simulate", "multiview", *RECIPES[name].split(), "--format",
                                              "colmap", "-o", str(folder)]
    print(f"[{name}] making the input: {' '.join(argv[-len(RECIPES[name].split()) - 4:])}", flush=True)
    subprocess.run(argv, check=True)
    return folder


def input_counts(database: Path) -> dict:
    """Pairs and verified (inlier) matches of a COLMAP database."""
    with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as db:
        pairs, matches = db.execute("SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM two_view_geometries "
                                    "WHERE rows > 0").fetchone()
        images = db.execute("SELECT COUNT(*) FROM images").fetchone()[0]
    return {"images": images, "pairs": pairs, "matches": matches}


def run_rotonly(folder: Path, work: Path, jobs: int, timeout: float | None, consensus: str = "auto") -> dict:
    out = work / "rotonly_out"
    if out.exists():
        shutil.rmtree(out)
    # evaluated here, as the mapper's model is: with --gt the run would also read the simulation's
    # ground truth (1 GB of JSON with its points at 1000 views, 6 s to skip them) in its own time
    argv = tool_runs.rotonly_command() + ["-q", "run", str(folder / "database.db"), "-o", str(out),
                                              "--jobs", str(jobs), "--consensus", consensus]
    # each stage's own peak in resources.json; the process's peak is then the largest of them
    # and of what the kernel reports (since the last reset: export and the exit)
    result = timed_process(argv, work / "rotonly.log", timeout, env={**os.environ, "ROTONLY_STAGE_PEAKS": "1"})
    reports = out / "reports"
    if result["exit"] == 0 and (reports / "run.json").is_file():
        run = json.loads((reports / "run.json").read_text())
        evaluated = tool_runs.evaluate_scene("rotonly", ground_truth(folder),
                                                 detect.read_scene(out / "sfm_data.json", poses_only=True), None)
        result.update(registered=run.get("num_registered"), points=run.get("num_points"),
                      rotation_mean_deg=evaluated.rotation_mean_deg, position_mean=evaluated.position_mean)
        resources = reports / "resources.json"
        if resources.is_file():
            result["stages"] = json.loads(resources.read_text())
            peaks = [s["peak_rss_mb"] for s in result["stages"].values() if s.get("peak_rss_mb")]
            result["peak_rss_mb"] = max([result["peak_rss_mb"], *peaks])
    return result


_GT: dict[Path, object] = {}


def ground_truth(folder: Path):
    """The recipe's ground truth (poses; read once per recipe)."""
    if folder not in _GT:
        _GT.clear()
        _GT[folder] = detect.read_ground_truth(folder / "gt" / "sfm_data.json")
    return _GT[folder]


def run_mapper(folder: Path, work: Path, jobs: int, timeout: float | None) -> dict:
    import pycolmap

    with tempfile.TemporaryDirectory(prefix="scale_glomap_", dir=work) as tmp:
        db_copy = Path(tmp) / "database.db"
        shutil.copyfile(folder / "database.db", db_copy)  # Database.open rewrites the header even to read
        argv = tool_runs.mapper_worker_command(db_copy, Path(tmp) / "work", jobs, 0)
        result = timed_process(argv, work / "mapper.log", timeout)
        best = Path(tmp) / "work" / "best"
        if result["exit"] == 0 and best.is_dir():
            rec = pycolmap.Reconstruction(str(best))
            evaluated = tool_runs.evaluate_scene("mapper", ground_truth(folder),
                                                     tool_runs.reconstruction_scene(rec), None)
            result.update(registered=rec.num_reg_images(), points=rec.num_points3D(),
                          rotation_mean_deg=evaluated.rotation_mean_deg, position_mean=evaluated.position_mean)
    return result


def fmt(value, digits: int = 1) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def tables(rows: list[dict]) -> str:
    lines = ["### Whole runs (median wall time of the rounds; peak RSS of the process)", "",
             "| recipe | images | pairs | inlier matches | method | exit | wall s | ratio | peak RSS MB "
             "| bytes / match "
             "| registered | points | rotation mean deg | position mean |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        counts = row["counts"]
        mapper = row.get("mapper") or {}
        mapper_wall = mapper.get("wall_s") if mapper.get("exit") == 0 else None  # a killed mapper: no ratio
        mode = row.get("consensus", "auto")
        rotonly_label = "rotonly run" + ("" if mode == "auto" else f" --consensus {mode}")
        for method in ("rotonly", "mapper"):
            r = row.get(method)
            if not r:
                continue
            ratio = r["wall_s"] / mapper_wall if method == "rotonly" and mapper_wall and r.get("exit") == 0 else None
            per_match = r["peak_rss_mb"] * 1048576 / counts["matches"] if r.get("peak_rss_mb") and counts["matches"] \
                else None
            lines.append(f"| {row['recipe']} | {counts['images']} | {counts['pairs']} | {counts['matches']} | "
                         f"{rotonly_label if method == 'rotonly' else 'pycolmap global mapper'} | {r.get('exit')} | "
                         f"{fmt(r['wall_s'])} | {fmt(ratio, 2)} | {fmt(r.get('peak_rss_mb'), 0)} | "
                         f"{fmt(per_match, 0)} | {fmt(r.get('registered'))} | {fmt(r.get('points'))} | "
                         f"{fmt(r.get('rotation_mean_deg'), 4)} | {fmt(r.get('position_mean'), 4)} |")
    lines += ["", "### rotonly per stage: wall time s / peak RSS MB (reports/resources.json)", "",
              "| recipe | " + " | ".join(STAGES) + " |", "|---|" + "---|" * len(STAGES)]
    for row in rows:
        stages = (row.get("rotonly") or {}).get("stages") or {}
        cells = [f"{fmt(stages[s]['time_s'])} / {fmt(stages[s]['peak_rss_mb'], 0)}" if s in stages else "–"
                 for s in STAGES]
        lines.append(f"| {row['recipe']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipes", nargs="+", default=["circular-200", "circular-1000"], choices=sorted(RECIPES))
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2, help="rotonly --jobs and the mapper's threads")
    parser.add_argument("--cache", type=Path, default=Path("results/scale_inputs"))
    parser.add_argument("-o", "--output", type=Path, default=Path("results/scale"))
    parser.add_argument("--no-mapper", action="store_true")
    parser.add_argument("--mapper-only", action="store_true",
                        help="run the mapper only; rotonly's rows are taken from OUTPUT/results.json (an earlier "
                             "invocation on the same recipes)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per process (killed after)")
    parser.add_argument("--results-md", type=Path, default=None)
    parser.add_argument("--consensus", choices=["auto", "full", "fast"], default="auto",
                        help="rotonly run's --consensus")
    parser.add_argument("--section", default="scale",
                        help="the section of --results-md the table replaces (one per set of recipes)")
    args = parser.parse_args(argv)
    tool_runs.byte_compile_rotonly()
    args.cache.mkdir(parents=True, exist_ok=True)
    args.output.mkdir(parents=True, exist_ok=True)
    rows = []
    earlier = {}
    if args.mapper_only:
        earlier = {row["recipe"]: row for row in json.loads((args.output / "results.json").read_text())}
    for name in args.recipes:
        folder = make_input(name, args.cache)
        row = {"recipe": name, "counts": input_counts(folder / "database.db"), "rounds": [],
               "consensus": args.consensus}
        work = args.output / name
        work.mkdir(parents=True, exist_ok=True)
        methods = ["mapper"] if args.mapper_only else ["rotonly"] + ([] if args.no_mapper else ["mapper"])
        for k in range(args.rounds):
            done = {}
            for method in methods[k % len(methods):] + methods[:k % len(methods)]:
                print(f"[{name}] round {k + 1}: {method}", flush=True)
                if method == "rotonly":
                    done[method] = run_rotonly(folder, work, args.jobs, args.timeout, args.consensus)
                else:
                    done[method] = run_mapper(folder, work, args.jobs, args.timeout)
                print(f"[{name}]   {json.dumps({key: v for key, v in done[method].items() if key != 'stages'})}",
                      flush=True)
            row["rounds"].append(done)
        for method in methods:  # the round of median wall time
            runs = sorted((r[method] for r in row["rounds"]), key=lambda r: r["wall_s"])
            row[method] = runs[len(runs) // 2]
        if args.mapper_only:
            row["rotonly"] = earlier[name]["rotonly"]
            row["rounds"] = [{**old, **new} for old, new in zip(earlier[name]["rounds"], row["rounds"])]
        rows.append(row)
        (args.output / "results.json").write_text(json.dumps(rows, indent=1))
    table = tables(rows)
    if args.mapper_only:
        table = ("The mapper's rows from this command; rotonly's from the same command without --mapper-only, run "
                 "before it into the same RESULTS (its results.json).\n\n" + table)
    print(table)
    title = "Scale: rotonly run against the global mapper on simulated collections"
    results_md.record(args.results_md, args.section, title if args.section == "scale" else f"{title} ({args.section})",
                      results_md.command_line("python scripts/bench/scale.py", argv), table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
