"""`rotonly run INPUT -o OUT [--gt GT]`: the whole rotation-only SfM chain."""

from __future__ import annotations

import gc
import sys
from pathlib import Path

import click

from rotonly_cli.cli import options as cli_options


def run_options(ctx: click.Context, **settings):
    """RunOptions of the command's options (``settings``, by their names: options.settings),
    with the progress bars on a terminal."""
    from rotonly_cli.options import RunOptions
    from rotonly_cli.options.settings import with_settings

    return with_settings(RunOptions(), {**settings, "progress": show_progress(ctx)})


def show_progress(ctx: click.Context) -> bool:
    """Progress bars: on a terminal, unless -q."""
    return sys.stderr.isatty() and (ctx.find_root().obj or {}).get("verbosity", 0) >= 0


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
    if summary.get("reprojection_error_px") is not None:
        parts.append(f"reprojection error {summary['reprojection_error_px']:.2f} px")
    click.echo(", ".join(parts))
    for component in summary.get("components", [])[1:]:
        if component["model"]:  # another part of the view graph, written as its own model
            click.echo(f"  another component: {component['num_registered']}/{component['num_views']} views, "
                       f"{component['num_points']} points: {out_dir / component['model']}, "
                       f"{out_dir / component['sfm_data']}")
    echo_intrinsics(summary)


def echo_intrinsics(summary: dict, max_cameras: int = 4) -> None:
    """Per camera the intrinsics the run started from and ended with (the first
    ``max_cameras``; all in reports/intrinsics.json), then each warning on its own line."""
    cameras = summary.get("intrinsics") or {}
    for camera_id, camera in list(cameras.items())[:max_cameras]:
        start, end = (" ".join(f"{v:.6g}" for v in params) for params in (camera["start"], camera["end"]))
        models = camera["model"][0] if camera["model"][0] == camera["model"][1] else " -> ".join(camera["model"])
        click.echo(f"  camera {camera_id} ({models}): " + (f"[{start}] unchanged" if start == end
                                                           else f"[{start}] -> [{end}]"))
    if len(cameras) > max_cameras:
        click.echo(f"  ... {len(cameras) - max_cameras} more cameras in reports/intrinsics.json")
    for warning in summary.get("warnings", []):
        click.echo(f"warning: {warning}")


def chain_command(name: str, summary: str, stages: tuple[str, ...] | None, *options) -> click.Command:
    """A command that runs the chain on INPUT into the workspace OUT: ``rotonly run`` (every
    stage: ``stages`` None) and ``rotonly identify`` (the first two). ``options``: the
    command's own click options, in --help order, between -o and --jobs (then --cluster)."""

    def callback(ctx: click.Context, input_path: Path, out_dir: Path, no_grrm: bool = False, **settings) -> None:
        collecting = gc.isenabled()
        gc.disable()  # from the imports on: see runtime.startup.collector_paused
        try:
            from rotonly_cli.pipeline import run_pipeline

            options = run_options(ctx, grrm=not no_grrm, **settings)
            summary = (run_pipeline(input_path, out_dir, options) if stages is None
                       else run_pipeline(input_path, out_dir, options, stages=stages))
        finally:
            if collecting:
                gc.enable()
        echo_summary(summary, out_dir)

    decorators = [click.argument("input_path", metavar="INPUT", type=click.Path(path_type=Path)),
                  click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path),
                               help="Workspace folder (new, empty, or a previous rotonly workspace: replaced "
                                    "atomically)."),
                  *options, cli_options.jobs, cli_options.cluster, click.pass_context]
    for decorator in reversed(decorators):
        callback = decorator(callback)
    return click.command(name, help=summary)(callback)


command = chain_command("run", """Reconstruct camera poses and 3D points from feature matches.

    INPUT is a COLMAP database (.db) or an OpenMVG sfm_data.json (with --matches-dir).
    Chain: relative poses (every edge re-estimated by calibrated RANSAC; --reestimate auto
    keeps stored E-based ones) -> scene identification -> TRRM per edge -> robust rotation
    averaging -> GRRM -> LiGT centres -> triangulation. OUT receives sfm_data.json (OpenMVG),
    sparse/ (COLMAP model), view_graph.json, reports/<stage>.json, run.log and state.npz (for
    the stage commands).
    Views outside the largest connected view graph component are reported, not registered.
    """, None, cli_options.gt, cli_options.load_options, cli_options.max_residual_deg,
                        click.option("--no-grrm", is_flag=True, help="Skip GRRM (keep the averaged rotations)."),
                        cli_options.max_memory)
