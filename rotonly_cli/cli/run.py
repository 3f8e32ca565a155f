"""`rotonly run INPUT -o OUT [--gt GT]`: the whole rotation-only SfM chain."""

from __future__ import annotations

import gc
import sys
from pathlib import Path

import click

from rotonly_cli.stages.load import REESTIMATE_MODES


def _usable_cpus() -> int:
    from rotonly_cli.runtime.parallel import usable_cpus

    return usable_cpus()


def shared_load_options(function):
    """Options of the load stage, shared by `run` and `identify`."""
    options = [
        click.option("--matches-dir", type=click.Path(path_type=Path), default=None,
                     help="OpenMVG input: folder with <view>.feat and matches.e/f/putative .bin|.txt "
                          "(default: the sfm_data.json folder)."),
        click.option("--image-path", type=click.Path(path_type=Path), default=None,
                     help="Images, for point colours (default: images/ beside a database, root_path of "
                          "an OpenMVG project; missing images give grey points)."),
        click.option("--min-inliers", type=click.IntRange(min=6), default=30, show_default=True,
                     help="Edges with fewer inlier matches are filtered."),
        click.option("--reestimate", type=click.Choice(REESTIMATE_MODES), default="auto", show_default=True,
                     help="Re-estimate relative poses with calibrated RANSAC: auto = edges without an "
                          "E-based stored pose (PLANAR/UNCALIBRATED/... or none stored)."),
        click.option("--ransac-max-error", type=click.FloatRange(min=0, min_open=True), default=2.0,
                     show_default=True, help="RANSAC threshold in pixels."),
        click.option("--seed", type=int, default=0, show_default=True, help="RANSAC seed (runs are deterministic)."),
    ]
    for option in reversed(options):
        function = option(function)
    return function


def jobs_option(function):
    """``--jobs N`` (an int: the usable CPUs when not given)."""
    return click.option("--jobs", type=click.IntRange(min=1), default=None,
                        callback=lambda ctx, param, value: _usable_cpus() if value is None else value,
                        help="Processes for scene identification and TRRM (forked, Linux; default: the "
                             "usable CPUs). The numbers do not depend on it. Both stay in one process while "
                             "images are being decoded for the point colours (a fork is unsafe with a "
                             "thread running).")(function)


def run_options(ctx: click.Context, matches_dir, image_path, min_inliers, reestimate, ransac_max_error, seed,
                **extra):
    from rotonly_cli.pipeline import RunOptions
    from rotonly_cli.stages.average import AverageOptions
    from rotonly_cli.stages.load import LoadOptions

    quiet = (ctx.obj or {}).get("verbosity", 0) < 0
    load = LoadOptions(reestimate=reestimate, ransac_max_error_px=ransac_max_error, seed=seed,
                       min_inliers=min_inliers)
    average = AverageOptions(max_residual_deg=extra.pop("max_residual_deg", AverageOptions.max_residual_deg))
    return RunOptions(matches_dir=None if matches_dir is None else str(matches_dir),
                      image_path=None if image_path is None else str(image_path), load=load, average=average,
                      progress=sys.stderr.isatty() and not quiet, **extra)


def echo_summary(summary: dict, out_dir: Path) -> None:
    """One line: registered views, points, edges, time (and the eval numbers with --gt)."""
    if "num_registered" not in summary:
        click.echo(f"{out_dir}: {summary['stages'][-1]} done, {summary['num_active_edges']} active edges, "
                   f"{summary['time_s']:.1f} s")
        return
    parts = [f"{out_dir}: {summary['num_registered']}/{summary['num_views']} views registered",
             f"{summary['num_points']} points", f"{summary['num_active_edges']} active edges",
             f"{summary['time_s']:.1f} s"]
    rotation = summary.get("rotation_error_deg")
    if rotation:
        parts.append(f"rotation error mean {rotation['mean']:.4f} deg, median {rotation['median']:.4f} deg")
    if summary.get("unregistered_views"):
        parts.append(f"not registered: views {summary['unregistered_views']}")
    click.echo(", ".join(parts))


@click.command("run")
@click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path),
              help="Workspace folder (new, empty, or a previous rotonly workspace: replaced atomically).")
@click.option("--gt", "gt_path", type=click.Path(path_type=Path), default=None,
              help="Ground truth (Strecha folder, sfm_data.json or COLMAP model): writes OUT/eval/report.{json,html}.")
@shared_load_options
@click.option("--max-residual-deg", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True,
              help="Edges further than this from the averaged rotations are filtered as outliers.")
@click.option("--no-grrm", is_flag=True, help="Skip GRRM (keep the averaged rotations).")
@jobs_option
@click.pass_context
def command(ctx: click.Context, input_path: Path, out_dir: Path, gt_path: Path | None, no_grrm: bool,
            jobs: int, **load_options) -> None:
    """Reconstruct camera poses and 3D points from feature matches.

    INPUT is a COLMAP database (.db) or an OpenMVG sfm_data.json (with --matches-dir).
    Chain: relative poses (stored E-based ones kept, others re-estimated) -> scene
    identification -> TRRM per edge -> robust rotation averaging -> GRRM -> LiGT centres ->
    triangulation. OUT receives sfm_data.json (OpenMVG), sparse/ (COLMAP model),
    view_graph.json, reports/<stage>.json, run.log and state.npz (for the stage commands).
    Views outside the largest connected view graph component are reported, not registered.
    """
    collecting = gc.isenabled()
    gc.disable()  # from the imports on: see runtime.startup.collector_paused
    try:
        from rotonly_cli.pipeline import run_pipeline

        options = run_options(ctx, grrm=not no_grrm, gt=None if gt_path is None else str(gt_path),
                              jobs=jobs, **load_options)
        summary = run_pipeline(input_path, out_dir, options)
    finally:
        if collecting:
            gc.enable()
    echo_summary(summary, out_dir)
