"""Two-view Monte-Carlo benchmark in the paper's set-up (rotation_only.tex §"Default Settings",
§"Two-view Rotation Optimization").

Per scene (the five two-view scenes) and noise level (pixel noise of magnitude U(0, n),
960×960 images, focal 800 px), ``trials`` problems:

* initial: 5-point + RANSAC (OpenCV; rotonly_cli.simulation.fivepoint), its inliers kept;
* BA (points + pose), PA (eq:PAtotal2), Kneip eigen (λ_min over R), Kneip nonlinear
  (OpenGV-style 6-DoF), TRRM (``twoview.refine_rotations``) — all from the initial pose on the
  inliers.

BA, PA and Kneip nonlinear run per edge in the worker processes (time per edge measured there);
Kneip eigen and TRRM run batched over all trials of a cell (time = batch time / trials).
Scene identification at the initial rotation is scored against the scene's expected kind.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from rotonly_cli.bench.common import (
    CellCheckpoint,
    error_deg,
    fmt,
    markdown_table,
    parallel_map,
    plot_curves,
    stats,
    write_json,
)

SCENES = ("standard", "planar", "holoplane", "rankregular_line", "pure_rotation")
EXPECTED_KIND = {"standard": "REGULAR", "planar": "REGULAR", "holoplane": "ROTATION_SINGULAR",
                 "rankregular_line": "ROTATION_SINGULAR", "pure_rotation": "PURE_ROTATION"}
METHODS = ("initial", "BA", "PA", "Kneip eigen", "Kneip nonlinear", "TRRM")
PER_EDGE_METHODS = ("BA", "PA", "Kneip nonlinear")


@dataclass
class Trial:
    R_true: np.ndarray
    R_init: np.ndarray
    t_init: np.ndarray
    x_i: np.ndarray  # RANSAC inliers
    x_j: np.ndarray
    ransac_ok: bool
    rotations: dict  # per-edge method -> R_j_from_i
    seconds: dict  # per-edge method -> time


def refine_per_edge(R_init: np.ndarray, t_init: np.ndarray, x_i: np.ndarray, x_j: np.ndarray,
                    methods=PER_EDGE_METHODS) -> tuple[dict, dict]:
    """Run the per-edge two-view baselines from (R_init, t_init); returns rotations and times."""
    from rotonly_cli.baselines.opengv_nonlinear import optimize_nonlinear_twoview
    from rotonly_cli.baselines.pa import pose_adjust_twoview
    from rotonly_cli.baselines.twoview_ba import bundle_adjust_twoview

    fns = {"BA": bundle_adjust_twoview, "PA": pose_adjust_twoview, "Kneip nonlinear": optimize_nonlinear_twoview}
    t = t_init if np.linalg.norm(t_init) > 0 else np.array([1.0, 0.0, 0.0])
    rotations, seconds = {}, {}
    with np.errstate(all="ignore"):
        for name in methods:
            start = time.perf_counter()
            try:
                rotations[name] = fns[name](R_init, t, x_i, x_j).R_j_from_i
            except (ValueError, np.linalg.LinAlgError):  # a degenerate edge: counted as the start
                rotations[name] = R_init
            seconds[name] = time.perf_counter() - start
    return rotations, seconds


def run_trial(args: tuple) -> Trial:
    """Simulate, initialise with 5-point RANSAC and run the per-edge baselines (one pool task)."""
    from rotonly_cli.simulation.fivepoint import five_point_ransac
    from rotonly_cli.simulation.pair_scenes import simulate_twoview

    scene, noise_px, seed, num_points, per_edge_methods = args
    problem = simulate_twoview(scene, num_points=num_points, noise_px=noise_px, rng=seed)
    estimate = five_point_ransac(problem.x_i, problem.x_j, problem.focal,
                                 threshold_px=max(1.0, 2.0 * noise_px), seed=seed % (2**31))
    if estimate.success and estimate.num_inliers >= 6:
        x_i, x_j = problem.x_i[estimate.inlier_mask], problem.x_j[estimate.inlier_mask]
        R_init, t_init = estimate.R_j_from_i, estimate.t_direction
    else:  # counted as a failure; the optimisers start from the identity on all points
        x_i, x_j, R_init, t_init = problem.x_i, problem.x_j, np.eye(3), np.array([1.0, 0.0, 0.0])
    rotations, seconds = refine_per_edge(R_init, t_init, x_i, x_j, per_edge_methods)
    return Trial(problem.R_j_from_i, R_init, t_init, x_i, x_j, bool(estimate.success), rotations, seconds)


def _kinds(identification) -> list[str]:
    return [str(getattr(item.kind, "value", item.kind)) for item in identification]


def run_cell(scene: str, noise_px: float, trials: int, num_points: int, seed0: int, jobs: int,
             progress: bool, methods: tuple[str, ...] = METHODS) -> dict:
    """One (scene, noise) cell: the errors of ``methods`` ("initial" always included; the
    seeds, hence the problems and the 5-point starts, do not depend on the selection)."""
    from rotonly_cli import twoview
    from rotonly_cli.baselines.kneip import refine_kneip_eigen
    from rotonly_cli.geometry import pairwise as pg

    seeds = [seed0 + 1_000_003 * SCENES.index(scene) + 10_007 * int(round(noise_px * 10)) + k for k in range(trials)]
    methods = ("initial",) + tuple(m for m in METHODS[1:] if m in methods)
    per_edge = tuple(m for m in PER_EDGE_METHODS if m in methods)
    results: list[Trial] = parallel_map(run_trial, [(scene, noise_px, s, num_points, per_edge) for s in seeds], jobs,
                                        f"twoview {scene} {noise_px:g}px", progress)
    R_true = np.stack([r.R_true for r in results])
    R_init = np.stack([r.R_init for r in results])
    x_i = [r.x_i for r in results]
    x_j = [r.x_j for r in results]
    rotations = {"initial": R_init}
    seconds = {"initial": 0.0}
    for name in per_edge:
        rotations[name] = np.stack([r.rotations[name] for r in results])
        seconds[name] = float(np.mean([r.seconds[name] for r in results]))
    if "Kneip eigen" in methods:
        start = time.perf_counter()
        with np.errstate(all="ignore"):
            rotations["Kneip eigen"] = refine_kneip_eigen(R_init, pg.pack_edges(x_i, x_j)).rotations
        seconds["Kneip eigen"] = (time.perf_counter() - start) / trials
    if "TRRM" in methods:
        start = time.perf_counter()
        rotations["TRRM"] = np.asarray(twoview.refine_rotations(R_init, x_i, x_j).rotations)
        seconds["TRRM"] = (time.perf_counter() - start) / trials
    identification = _kinds(twoview.identify_scenes(R_init, x_i, x_j))
    errors = {m: error_deg(rotations[m], R_true) for m in methods}
    return dict(scene=scene, noise_px=noise_px, trials=trials,
                ransac_failures=int(sum(not r.ransac_ok for r in results)),
                identification_accuracy=float(np.mean([k == EXPECTED_KIND[scene] for k in identification])),
                methods={m: {**stats(errors[m]), "ms_per_edge": 1e3 * seconds[m]} for m in methods},
                errors_deg={m: errors[m].tolist() for m in methods})


def _methods_of(rows: list[dict]) -> tuple[str, ...]:
    return tuple(m for m in METHODS if m in rows[0]["methods"]) if rows else METHODS


def format_table(rows: list[dict]) -> str:
    methods = _methods_of(rows)
    head = ["scene", "noise px", "trials"] + [f"{m} mean/median" for m in methods] + ["best", "ident. acc."]
    lines = []
    for r in rows:
        means = ({m: r["methods"][m]["mean"] for m in methods if m != "initial"}
                 or {"initial": r["methods"]["initial"]["mean"]})
        best = min(means, key=lambda m: means[m] if np.isfinite(means[m]) else np.inf)
        cells = [r["scene"], f"{r['noise_px']:g}", str(r["trials"])]
        cells += [f"{fmt(r['methods'][m]['mean'])} / {fmt(r['methods'][m]['median'])}" for m in methods]
        cells += [best, f"{100 * r['identification_accuracy']:.0f}%"]
        lines.append(cells)
    table = markdown_table(head, lines)
    time_head = ["scene", "noise px"] + [f"{m} ms/edge" for m in methods[1:]]
    time_rows = [[r["scene"], f"{r['noise_px']:g}"] + [f"{r['methods'][m]['ms_per_edge']:.2f}" for m in methods[1:]]
                 for r in rows]
    return (f"Rotation error (deg) vs ground truth, mean / median over trials\n\n{table}\n\n"
            f"Time per edge (BA, PA, Kneip nonlinear: per edge in one process; Kneip eigen and TRRM: "
            f"batched over the cell)\n\n{markdown_table(time_head, time_rows)}")


def run(out_dir, scenes=SCENES, noise_levels=(0.5, 1.0, 2.0, 5.0), trials: int = 100, num_points: int = 1000,
        seed: int = 0, jobs: int = 1, progress: bool = True, methods: tuple[str, ...] = METHODS) -> tuple[str, dict]:
    """Run the benchmark; write table.md, results.json and error_vs_noise.png into ``out_dir``.
    ``methods``: a subset of METHODS to run ("initial" always is), e.g. the cheap ones for many trials."""
    from rotonly_cli.bench.common import result_dir

    started = time.perf_counter()
    checkpoint = CellCheckpoint(out_dir, dict(trials=trials, num_points=num_points, seed=seed, methods=list(methods)))
    rows = [checkpoint.get_or_run((scene, float(noise)), lambda scene=scene, noise=noise: run_cell(
                scene, float(noise), trials, num_points, seed, jobs, progress, methods))
            for scene in scenes for noise in noise_levels]
    config = dict(scenes=list(scenes), noise_levels_px=list(noise_levels), trials=trials, num_points=num_points,
                  methods=list(_methods_of(rows)),
                  seed=seed, image_size=[960, 960], focal_px=800.0, noise_model="magnitude U(0, n) px",
                  initial="OpenCV 5-point RANSAC, threshold max(1, 2n) px, inliers only")
    table = (f"# rotonly bench twoview\n\n{trials} trials per cell, {num_points} points, 960x960 px, f = 800 px, "
             f"noise magnitude U(0, n) px.\n\n" + format_table(rows) + "\n")
    payload = dict(config=config, rows=rows, seconds=time.perf_counter() - started)
    with result_dir(out_dir) as tmp:
        (tmp / "table.md").write_text(table)
        write_json(tmp / "results.json", payload)
        for stat in ("mean", "median"):
            panels = {scene: {m: ([r["noise_px"] for r in rows if r["scene"] == scene],
                                  [r["methods"][m][stat] for r in rows if r["scene"] == scene])
                              for m in _methods_of(rows)}
                      for scene in scenes}
            plot_curves(tmp / f"error_vs_noise_{stat}.png", panels, "noise (px)", f"{stat} rotation error (deg)",
                        f"Two-view rotation error ({stat}) vs noise")
    checkpoint.remove()
    return table, payload
