"""Why GRRM can end worse than its own start on the scale benchmark's simulated scenes.

scripts/bench/scale.py's scene (``simulate_multiview(setup, num_views, points_per_view x
num_views, window, max_height, init="perturbed")``, no wrong matches), written as a COLMAP
database and run through rotonly's load, identify, refine and average stages. Then GRRM on
the same view graph, one thing changed per row:

* the default (Geman-McClure at ``loss_scale_factor`` x the start's robust residual scale);
* started from the ground-truth rotations (is it the start or the objective's optimum?);
* wider losses (``loss_scale_factor`` 3 and 10) and no robust loss at all;
* every edge's t_ij held at its ground-truth direction (grrm_fixed_translations: an oracle);
* t_ij held at the directions of LiGT's centres (from GRRM's rotations, and from the GT ones).

    python scripts/research/probe_grrm_simulation.py --views 100
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

import grrm_fixed_translations as fixed


def simulated_run(views: int, points_per_view: int, setup: str, window: int, max_height: float, seed: int,
                  directory: Path):
    """(run after average, R_gt (n, 3, 3), C_gt (n, 3)) in the run's view order."""
    from rotonly_cli.io.colmap import write_database
    from rotonly_cli.pipeline import STAGE_FUNCTIONS, RunOptions, load_stage
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    problem = simulate_multiview(setup, num_views=views, num_points=points_per_view * views, window=window,
                                 max_height=max_height, init="perturbed", rng=seed)
    write_database(directory / "database.db", problem.scene)
    run = load_stage(directory / "database.db", RunOptions(progress=False))
    for stage in ("identify", "refine", "average"):
        STAGE_FUNCTIONS[stage](run)
    by_name = {problem.scene.views[v].name: problem.gt_poses[v] for v in problem.gt_poses}
    poses = [by_name[run.graph.views[v].name] for v in run.graph.view_ids()]
    return run, np.stack([p.R_cam_from_world for p in poses]), np.stack([p.center for p in poses])


def mean_error_deg(R: np.ndarray, R_gt: np.ndarray) -> float:
    """Mean geodesic error after the best global rotation (`rotonly eval`'s rotation metric)."""
    from rotonly_cli.geometry import alignment

    return float(alignment.rotation_errors_after_alignment(R, R_gt)[0].mean())


def edge_directions(graph, R: np.ndarray, C: np.ndarray) -> dict[int, np.ndarray]:
    """Unit t_ij = R_j (c_i - c_j) of every edge of ``graph`` from the poses (view order)."""
    index = {v: k for k, v in enumerate(graph.view_ids())}
    out = {}
    for k, edge in enumerate(graph.edges):
        i, j = index[edge.i], index[edge.j]
        t = R[j] @ (C[i] - C[j])
        out[k] = t / np.linalg.norm(t)
    return out


def rows(run, R_gt: np.ndarray, C_gt: np.ndarray) -> list[tuple[str, float]]:
    from rotonly_cli.stages.optimize import optimize_graph
    from rotonly_cli.stages.translate import translate_graph

    graph, normalized, options = run.graph, run.scene.normalized, run.options.optimize

    def grrm(start: np.ndarray, **changes) -> np.ndarray:
        return optimize_graph(graph, normalized, start, replace(options, **changes))[0]

    averaged = run.rotations
    default = grrm(averaged)
    table = [("L1-IRLS average (GRRM start)", mean_error_deg(averaged, R_gt)),
             ("GRRM", mean_error_deg(default, R_gt)),
             ("GRRM from the GT rotations", mean_error_deg(grrm(R_gt), R_gt))]
    for factor in (3.0, 10.0):
        table.append((f"GRRM, loss_scale_factor {factor:g}",
                      mean_error_deg(grrm(averaged, loss_scale_factor=factor), R_gt)))
    table.append(("GRRM, no robust loss", mean_error_deg(grrm(averaged, loss="none"), R_gt)))
    held = fixed.optimize_graph_with_translations(graph, normalized, averaged, edge_directions(graph, R_gt, C_gt))
    table.append(("GRRM, t_ij held at the GT directions", mean_error_deg(held, R_gt)))
    for label, rotations in (("GRRM's", default), ("the GT", R_gt)):
        centers, _ = translate_graph(graph, normalized, rotations, run.options.translate)
        held = fixed.optimize_graph_with_translations(graph, normalized, averaged,
                                                      edge_directions(graph, rotations, centers))
        table.append((f"GRRM, t_ij held at LiGT's (centres from {label} rotations)", mean_error_deg(held, R_gt)))
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--points-per-view", type=int, default=100)
    parser.add_argument("--setup", default="linear", choices=("circular", "square", "linear", "outward"))
    parser.add_argument("--window", type=int, default=5)
    parser.add_argument("--max-height", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="probe_grrm_simulation_") as directory:
        run, R_gt, C_gt = simulated_run(args.views, args.points_per_view, args.setup, args.window,
                                        args.max_height, args.seed, Path(directory))
        table = rows(run, R_gt, C_gt)
    print(f"| {args.setup}, {args.views} views, window {args.window} | mean rotation error (deg) |")
    print("|---|---|")
    for label, value in table:
        print(f"| {label} | {value:.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
