"""`rotonly refine FILE.npz | WORKSPACE`: TRRM on one simulated edge, or the refine stage.

A FILE ending in ``.npz`` (written by ``rotonly simulate twoview``) selects the simulation
mode: identify and TRRM-refine that edge, compared to its truth. A folder is an OUT workspace
of ``rotonly identify`` / ``rotonly run``: TRRM runs on all its active edges
(``pipeline.resume(WORKSPACE, "refine")``).
Initial rotation: ``--init ransac`` = OpenCV 5-point RANSAC on the normalized matches, the
optimisation then runs on its inliers (paper §"Default Settings"); ``--init truth-perturbed``
= the true rotation turned by ``--perturb-deg`` about a random axis, all matches.
"""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from rotonly_cli.cli import options as cli_options
from rotonly_cli.errors import AlgorithmError, InputError


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    from rotonly_cli.geometry import so3

    return float(np.rad2deg(so3.geodesic_angle(a, b)))


def _direction_error_deg(t_est: np.ndarray, t_true: np.ndarray) -> float:
    n_est, n_true = np.linalg.norm(t_est), np.linalg.norm(t_true)
    if n_est == 0 or n_true == 0:
        return float("nan")  # pure rotation: no direction to compare
    return float(np.rad2deg(np.arccos(np.clip(t_est @ t_true / (n_est * n_true), -1.0, 1.0))))


def refine_simulation(path: Path, init: str, perturb_deg: float, ransac_threshold_px: float, seed: int) -> dict:
    """Run identification + TRRM on the edge stored in ``path``; returns the table's numbers."""
    from rotonly_cli import twoview
    from rotonly_cli.simulation.fivepoint import five_point_ransac, perturbed_rotation
    from rotonly_cli.simulation.pair_scenes import load_twoview

    problem = load_twoview(path)
    x_i, x_j = problem.x_i, problem.x_j
    t_init = None
    if init == "ransac":
        estimate = five_point_ransac(x_i, x_j, problem.focal, threshold_px=ransac_threshold_px, seed=seed)
        if not estimate.success:
            raise AlgorithmError("5-point RANSAC found no relative pose; try --init truth-perturbed")
        R_init, t_init = estimate.R_j_from_i, estimate.t_direction
        x_i, x_j = x_i[estimate.inlier_mask], x_j[estimate.inlier_mask]
    else:
        R_init = perturbed_rotation(problem.R_j_from_i, perturb_deg, np.random.default_rng(seed))

    try:
        start = time.perf_counter()
        identification = twoview.identify_scene(R_init, x_i, x_j)
        time_identify = time.perf_counter() - start
        start = time.perf_counter()
        refinement = twoview.refine_rotation(R_init, x_i, x_j)
        time_refine = time.perf_counter() - start
    except ValueError as exc:  # e.g. fewer matches than the two-view core accepts
        raise AlgorithmError(f"{path}: two-view refinement impossible: {exc}") from exc
    kind = getattr(identification.kind, "value", identification.kind)
    return {
        "file": str(path), "scene": problem.scene, "noise_px": problem.noise_px, "matches": int(len(x_i)),
        "kind": str(kind), "detection_value": float(identification.detection_value),
        "initial_rotation_error_deg": _angle_deg(R_init, problem.R_j_from_i),
        "refined_rotation_error_deg": _angle_deg(refinement.rotation, problem.R_j_from_i),
        "initial_translation_error_deg": (_direction_error_deg(t_init, problem.t_j_from_i)
                                          if t_init is not None else float("nan")),
        "refined_translation_error_deg": _direction_error_deg(np.asarray(refinement.translation_direction),
                                                              problem.t_j_from_i),
        "iterations": int(refinement.iterations), "cost": float(refinement.cost),
        "time_identify_ms": 1e3 * time_identify, "time_refine_ms": 1e3 * time_refine,
    }


def format_table(row: dict) -> str:
    lines = [
        f"file                      {row['file']}",
        f"scene (simulated)         {row['scene']}  noise {row['noise_px']:g} px  matches {row['matches']}",
        f"identified kind           {row['kind']}",
        f"detection value v_rs      {row['detection_value']:.3e}",
        "",
        "| quantity                     | initial    | TRRM       |",
        "|------------------------------|------------|------------|",
        f"| rotation error (deg)         | {row['initial_rotation_error_deg']:10.5f} "
        f"| {row['refined_rotation_error_deg']:10.5f} |",
        f"| translation dir. error (deg) | {row['initial_translation_error_deg']:10.5f} "
        f"| {row['refined_translation_error_deg']:10.5f} |",
        "",
        f"iterations {row['iterations']}, cost {row['cost']:.3e}, "
        f"time identify {row['time_identify_ms']:.2f} ms, refine {row['time_refine_ms']:.2f} ms",
    ]
    return "\n".join(lines)


@click.command("refine")
@click.argument("target", type=click.Path(path_type=Path))
@click.option("--init", type=click.Choice(["ransac", "truth-perturbed"]), default="ransac", show_default=True,
              help="Initial rotation: OpenCV 5-point RANSAC (then its inliers), or the truth perturbed.")
@click.option("--perturb-deg", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Perturbation angle for --init truth-perturbed.")
@cli_options.ransac_max_error
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of RANSAC / the perturbation.")
@click.option("--json", "as_json", is_flag=True, help="Print the numbers as JSON.")
@cli_options.jobs
@click.pass_context
def command(ctx: click.Context, target: Path, init: str, perturb_deg: float, ransac_max_error: float, seed: int,
            as_json: bool, jobs: int) -> None:
    """TRRM-refine the edges of a workspace, or the simulated edge of a .npz file.

    \b
    TARGET = OUT workspace (folder from `rotonly identify INPUT -o OUT`): TRRM on every
             active edge, in place (state.npz, view_graph.json, reports/refine.json).
    TARGET = FILE.npz (from `rotonly simulate twoview`): prints the scene kind, v_rs, and the
             rotation / translation-direction errors before and after TRRM against the
             stored ground truth (the options below apply to this mode).
    """
    if target.is_dir():
        from rotonly_cli.cli.run import echo_summary, show_progress
        from rotonly_cli.io.workspace import STATE_FILE
        from rotonly_cli.options import RunOptions
        from rotonly_cli.pipeline import resume

        if not (target / STATE_FILE).is_file():
            raise InputError(f"folder is not a rotonly workspace (no {STATE_FILE}; make one with "
                             "`rotonly identify INPUT -o OUT`)", path=target, field="TARGET")
        echo_summary(resume(target, "refine", RunOptions(jobs=jobs, progress=show_progress(ctx))), target)
        return
    if target.suffix.lower() != ".npz":
        raise InputError("expected a workspace folder (from `rotonly identify`) or a .npz from "
                         "`rotonly simulate twoview`", path=target, field="TARGET")
    if ransac_max_error is None:
        ransac_max_error = cli_options.SIMULATION_RANSAC_MAX_ERROR_PX
    row = refine_simulation(target, init, perturb_deg, ransac_max_error, seed)
    if as_json:
        import json

        click.echo(json.dumps(row, indent=2))
    else:
        click.echo(format_table(row))
