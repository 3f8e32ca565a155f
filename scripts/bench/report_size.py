#!/usr/bin/env python3
"""Size of OUT/report.html on a collection of N views (issue 49 point 4: a per-image table of
10 000 rows must not make the page unusable).

A fake workspace is made without running the chain: N cameras along a street, each point seen
by three consecutive views, rotations 0.01-0.05 deg off the truth, edges to the next two
views (every 20th filtered), reports/*.json as `rotonly run` writes them, and with --gt the
evaluation (OUT/eval/) of the estimate against the truth. Then report.html is written and its
size and the time to write it printed.

    python scripts/bench/report_size.py --views 1000 10000 [--no-gt] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPOSITORY = Path(__file__).resolve().parents[2]
if str(REPOSITORY) not in sys.path:
    sys.path.insert(0, str(REPOSITORY))

from rotonly_cli.chain import STAGES, Run  # noqa: E402
from rotonly_cli.evaluation.run_report import REPORT_FILE, structure_statistics, write_run_report  # noqa: E402
from rotonly_cli.geometry import so3  # noqa: E402
from rotonly_cli.io.detect import InputKind  # noqa: E402
from rotonly_cli.options import RunOptions  # noqa: E402
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View  # noqa: E402
from rotonly_cli.scene.view_graph import Edge, ViewGraph  # noqa: E402

FOCAL, SIZE = 800.0, 960


def _truth(num_views: int) -> dict[int, Pose]:
    """Cameras about 1 apart along x, looking along +z; off the line by up to 0.3 (collinear
    centres leave evalQuality's similarity a free turn about the line)."""
    return {v: Pose(np.eye(3), np.array([float(v), 0.2 * np.cos(0.23 * v), 0.3 * np.sin(0.37 * v)]))
            for v in range(num_views)}


def fake_workspace(directory: Path, num_views: int, gt: bool = True, points_per_view: int = 10,
                   seed: int = 1) -> tuple[Run, SfMScene, object]:
    """Write reports/*.json (and eval/ with ``gt``) of a fake run of ``num_views`` views into
    ``directory``; returns (run, output scene, structure statistics) for write_run_report."""
    from rotonly_cli.io.workspace import write_report

    rng = np.random.default_rng(seed)
    truth = _truth(num_views)
    axes = rng.normal(size=(num_views, 3))
    turns = so3.exp(axes / np.linalg.norm(axes, axis=1, keepdims=True)
                    * np.radians(rng.uniform(0.01, 0.05, (num_views, 1))))
    estimate = {v: Pose(turns[v] @ p.R_cam_from_world, p.center + rng.normal(size=3) * 0.01)
                for v, p in truth.items()}
    views = {v: View(v, f"image_{v:05d}.jpg", 1) for v in range(num_views)}
    intrinsics = {1: Intrinsics(1, "PINHOLE", SIZE, SIZE, np.array([FOCAL, FOCAL, SIZE / 2, SIZE / 2]))}
    # points in front of view v, seen by v, v+1, v+2
    first = np.repeat(np.arange(max(num_views - 2, 0)), points_per_view)
    points = np.stack([first + 1.0 + rng.uniform(-0.5, 0.5, first.size), rng.uniform(-3, 3, first.size),
                       rng.uniform(8, 12, first.size)], axis=1)
    keypoints: dict[int, list] = {v: [] for v in views}
    observations = []
    for v0, X in zip(first, points):
        track = []
        for v in (v0, v0 + 1, v0 + 2):
            pose = truth[v]
            x = pose.R_cam_from_world @ (X - pose.center)
            keypoints[v].append(x[:2] / x[2] + rng.normal(size=2) * 0.5 / FOCAL)
            track.append((int(v), len(keypoints[v]) - 1))
        observations.append(track)
    normalized = {v: np.array(rows).reshape(-1, 2) for v, rows in keypoints.items()}
    pixels = {v: rows * FOCAL + SIZE / 2 for v, rows in normalized.items()}
    structure = Structure(np.arange(len(points)), points, np.full((len(points), 3), 128, np.uint8), observations)
    scene = SfMScene(views=views, intrinsics=intrinsics, poses=estimate, keypoints=pixels, normalized=normalized,
                     structure=structure, source="colmap-db")
    edges = []
    for i in range(num_views):
        for j in (i + 1, i + 2):
            if j < num_views:
                edge = Edge(i, j, np.eye(3), np.array([1.0, 0.0, 0.0]), np.zeros((40, 2), np.int64),
                            scene_kind="REGULAR")
                if (i + j) % 20 == 0:
                    edge.filter("rotation averaging outlier")
                edges.append(edge)
    graph = ViewGraph(views=views, edges=edges)
    options = RunOptions(gt=str(directory / "gt") if gt else None)
    run = Run(str(directory / "database.db"), InputKind.COLMAP_DB, scene, graph, options)
    statistics = structure_statistics(scene, graph.view_ids())
    stages = {name: {"time_s": 0.1 * (k + 1)} for k, name in enumerate(STAGES)}
    stages["load"].update(input=run.input_path, input_kind="colmap-db", num_views=num_views, num_pairs=len(edges))
    summary = {"input": run.input_path, "stages": list(STAGES), "num_views": num_views, "num_registered": num_views,
               "num_points": len(points), "num_active_edges": len(graph.active_edges()), "unregistered_views": [],
               "warnings": [], "time_s": 10.0, "components": [
                   {"model": "sparse", "sfm_data": "sfm_data.json", "num_views": num_views,
                    "num_registered": num_views, "num_points": len(points), "reason": ""}]}
    if gt:
        from rotonly_cli.evaluation.quality import evaluate
        from rotonly_cli.evaluation.report import write_report as write_eval_report

        truth_scene = SfMScene(views=views, intrinsics=intrinsics, poses=truth, source="colmap-model")
        evaluation = evaluate(truth_scene, scene)
        evaluation.gt_path, evaluation.estimate_path = options.gt, str(directory / "sfm_data.json")
        write_eval_report(evaluation, directory / "eval")
        summary["rotation_error_deg"] = evaluation.to_dict()["rotation_error_deg"]
    for name, report in {**stages, "export": {**statistics.report, "time_s": 0.5}, "run": summary}.items():
        write_report(directory, name, report)
    return run, scene, statistics


def measure(num_views: int, gt: bool, keep: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="rotonly-report-size-") as scratch:
        directory = (keep / f"v{num_views}") if keep else Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        run, scene, statistics = fake_workspace(directory, num_views, gt)
        started = time.perf_counter()
        path = write_run_report(directory, run, scene, statistics, list(STAGES))
        seconds = time.perf_counter() - started
        eval_html = directory / "eval" / "report.html"
        return {"views": num_views, "gt": gt, "report_html_bytes": path.stat().st_size, "seconds": round(seconds, 2),
                "eval_report_html_bytes": eval_html.stat().st_size if eval_html.is_file() else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--no-gt", action="store_true")
    parser.add_argument("--keep", type=Path, help="write the workspaces here (default: a temporary folder)")
    args = parser.parse_args()
    for num_views in args.views:
        print(json.dumps(measure(num_views, not args.no_gt, args.keep)), flush=True)


if __name__ == "__main__":
    main()

__all__ = ["REPORT_FILE", "fake_workspace", "measure"]
