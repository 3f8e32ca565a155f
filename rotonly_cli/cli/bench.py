"""``rotonly bench twoview|multiview|strecha``: the paper's experiment tables and figures,
side by side with the baselines (rotonly_cli.bench). Each writes RESULTS_DIR/{table.md,
results.json, *.png} and prints the table."""

from __future__ import annotations

import click

from rotonly_cli.bench import paper_multiview as bench_multiview
from rotonly_cli.bench import paper_strecha as bench_strecha
from rotonly_cli.bench import paper_twoview as bench_twoview


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise click.BadParameter(f"expected numbers, got {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise click.BadParameter("expected one or more non-negative numbers")
    return values


def _common(fn):
    fn = click.option("-o", "--output", "out_dir", required=True, type=click.Path(file_okay=False),
                      help="Results folder (table.md, results.json, *.png).")(fn)
    fn = click.option("--seed", type=int, default=0, show_default=True)(fn)
    fn = click.option("--jobs", type=click.IntRange(1, 64), default=1, show_default=True,
                      help="Worker processes.")(fn)
    fn = click.option("--quick", is_flag=True, help="Small smoke run (under a minute).")(fn)
    fn = click.option("--no-progress", is_flag=True,
                      help="No progress bar (there is none either when stderr is not a terminal, or with -q).")(fn)
    fn = click.option("--results-md", type=click.Path(dir_okay=False), default=None,
                      help="Also write the table into this file's section for this benchmark (docs/results.md).")(fn)
    return fn


def _progress(no_progress: bool) -> bool:
    """Progress bars: on a terminal, unless --no-progress or -q (in a log file tqdm's
    carriage-return redraws would be kept line after line)."""
    from rotonly_cli.cli.run import show_progress

    return not no_progress and show_progress(click.get_current_context())


def _record(results_md: str | None, key: str, title: str, table: str) -> None:
    from rotonly_cli.bench import results_md as md

    md.record(results_md, key, title, md.command_line("rotonly"), md.strip_title(table))


@click.group("bench")
def command() -> None:
    """Regenerate the paper's experiments with the baselines (two-view, multi-view, Strecha)."""


@command.command("twoview")
@_common
@click.option("--trials", type=click.IntRange(1), default=100, show_default=True, help="Monte-Carlo runs per cell.")
@click.option("--noise", default="0.5 1 2 5", show_default=True, help="Noise levels (px).")
@click.option("--scenes", default=",".join(bench_twoview.SCENES), show_default=True)
@click.option("--points", type=click.IntRange(10), default=1000, show_default=True)
@click.option("--methods", default=",".join(bench_twoview.METHODS[1:]), show_default=True,
              help="Methods to run after the 5-point start (always run); e.g. 'TRRM,Kneip eigen' for many "
                   "trials without the slow per-edge baselines. The problems do not depend on this choice.")
def twoview_cmd(out_dir, seed, jobs, quick, no_progress, results_md, trials, noise, scenes, points, methods) -> None:
    """Five two-view scenes x noise x (5-point, BA, PA, Kneip eigen, Kneip nonlinear, TRRM)."""
    scene_list = tuple(s.strip() for s in scenes.split(",") if s.strip())
    bad = [s for s in scene_list if s not in bench_twoview.SCENES]
    if bad:
        raise click.BadParameter(f"unknown scene(s) {bad}", param_hint="--scenes")
    method_list = tuple(m.strip() for m in methods.split(",") if m.strip())
    bad = [m for m in method_list if m not in bench_twoview.METHODS]
    if bad:
        raise click.BadParameter(f"unknown method(s) {bad}; choose from {list(bench_twoview.METHODS[1:])}",
                                 param_hint="--methods")
    noise_levels = _floats(noise)
    if quick:  # the paper's two-view optimisation scenes, 3 trials
        scene_list, noise_levels, trials, points = ("standard", "planar"), (1.0, 5.0), 3, 300
    table, _ = bench_twoview.run(out_dir, scene_list, noise_levels, trials, points, seed, jobs,
                                 _progress(no_progress), ("initial",) + method_list)
    click.echo(table)
    _record(results_md, "bench-twoview", "Two-view simulations (the paper's two-view tables)", table)


@command.command("multiview")
@_common
@click.option("--trials", type=click.IntRange(1), default=10, show_default=True)
@click.option("--noise", default="0.1 1 2 5 10", show_default=True, help="Noise levels (px).")
@click.option("--setups", default=",".join(bench_multiview.SETUPS), show_default=True)
@click.option("--views", type=click.IntRange(3), default=30, show_default=True)
@click.option("--points", type=click.IntRange(10), default=3000, show_default=True)
@click.option("--window", type=click.IntRange(1), default=5, show_default=True,
              help="Pairs: cameras at most this many apart along the trajectory.")
def multiview_cmd(out_dir, seed, jobs, quick, no_progress, results_md, trials, noise, setups, views, points,
                  window) -> None:
    """Circular / square / linear / outward x noise x (Chatterjee, ROBA, GRRM, pycolmap RA)."""
    setup_list = tuple(s.strip() for s in setups.split(",") if s.strip())
    bad = [s for s in setup_list if s not in bench_multiview.SETUPS]
    if bad:
        raise click.BadParameter(f"unknown set-up(s) {bad}", param_hint="--setups")
    noise_levels = _floats(noise)
    if quick:
        noise_levels, trials, views, points, window = (1.0, 5.0), 1, 12, 1200, 3
    table, _ = bench_multiview.run(out_dir, setup_list, noise_levels, trials, views, points, window, seed, jobs,
                                   _progress(no_progress))
    click.echo(table)
    _record(results_md, "bench-multiview", "Multi-view simulations (the paper's multi-view tables)", table)


@command.command("strecha")
@_common
@click.option("--root", required=True, type=click.Path(exists=True, file_okay=False),
              help="Folder of Strecha scenes (each with database.db and gt_dense_cameras/).")
@click.option("--no-mapper", is_flag=True, help="Skip the pycolmap global mapper reference.")
@click.option("--max-pairs", type=click.IntRange(1), default=None,
              help="Give rotonly at most this many verified pairs of each database (neighbours first).")
@click.option("--methods", default=",".join(bench_twoview.METHODS[1:]), show_default=True,
              help="Table 1's methods after the initial poses (always); e.g. 'TRRM,Kneip eigen,PA' without the "
                   "slow per-edge BA and Kneip nonlinear. The pairs and Table 2 do not depend on this choice.")
def strecha_cmd(out_dir, seed, jobs, quick, no_progress, results_md, root, no_mapper, max_pairs, methods) -> None:
    """Per-pair (table 1) and global (table 2) rotation errors vs Strecha GT, with published numbers,
    every row on the pairs `rotonly run` keeps before GRRM, and `rotonly run` as a row."""
    method_list = tuple(m.strip() for m in methods.split(",") if m.strip())
    bad = [m for m in method_list if m not in bench_twoview.METHODS]
    if bad:
        raise click.BadParameter(f"unknown method(s) {bad}; choose from {list(bench_twoview.METHODS[1:])}",
                                 param_hint="--methods")
    if quick:
        max_pairs = max_pairs or 12
    table, _ = bench_strecha.run(out_dir, root, jobs, seed, with_mapper=not no_mapper, max_pairs=max_pairs,
                                 progress=_progress(no_progress), methods=("initial",) + method_list)
    click.echo(table)
    _record(results_md, "bench-strecha", "Strecha: the paper's two-view and global tables with the baselines", table)
