"""Every click option used by more than one command, declared once; defaults come from
rotonly_cli/options.py.

=====================  ==============================================================
option                 commands
=====================  ==============================================================
--matches-dir          run, identify (OpenMVG input); convert has its own help
--image-path           run, identify, triangulate
--min-inliers          run, identify
--reestimate           run, identify
--ransac-max-error     run, identify
--seed (RANSAC)        run, identify
--max-residual-deg     run, average
--gt (GT_PATH)         run, triangulate
--jobs                 run, identify, refine
=====================  ==============================================================
"""

from __future__ import annotations

from pathlib import Path

import click

from rotonly_cli.options import REESTIMATE_MODES, AverageOptions, LoadOptions


def _all(*decorators):
    """One decorator applying ``decorators`` in the order written (top one first in --help)."""
    def apply(function):
        for decorator in reversed(decorators):
            function = decorator(function)
        return function
    return apply


class FiniteFloatRange(click.FloatRange):
    """click.FloatRange that also refuses nan and inf (which pass its comparisons)."""

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if number != number or number in (float("inf"), float("-inf")):
            self.fail(f"{number} is not a finite number.", param, ctx)
        return number


def _usable_cpus() -> int:
    from rotonly_cli.runtime.parallel import usable_cpus

    return usable_cpus()


matches_dir = click.option(
    "--matches-dir", type=click.Path(path_type=Path), default=None,
    help="OpenMVG input: folder with <view>.feat and matches.e/f/putative .bin|.txt (default: the sfm_data.json "
         "folder).")
image_path = click.option(
    "--image-path", type=click.Path(path_type=Path), default=None,
    help="Images, for point colours (default: images/ beside a database, root_path of an OpenMVG project; "
         "missing images give grey points).")
min_inliers = click.option(
    "--min-inliers", type=click.IntRange(min=6), default=LoadOptions.min_inliers, show_default=True,
    help="Edges with fewer inlier matches are filtered.")
reestimate = click.option(
    "--reestimate", type=click.Choice(REESTIMATE_MODES), default=LoadOptions.reestimate.value, show_default=True,
    help="Re-estimate relative poses with calibrated RANSAC: auto = edges without an E-based stored pose "
         "(PLANAR/UNCALIBRATED/... or none stored).")
ransac_max_error = click.option(
    "--ransac-max-error", type=FiniteFloatRange(min=0, min_open=True), default=LoadOptions.ransac_max_error_px,
    show_default=True, help="RANSAC threshold in pixels.")
seed = click.option("--seed", type=click.IntRange(0, 2 ** 31 - 1), default=LoadOptions.seed, show_default=True,
                    help="RANSAC seed (runs are deterministic).")
#: the load stage's options (`run` and `identify`)
load_options = _all(matches_dir, image_path, min_inliers, reestimate, ransac_max_error, seed)

max_residual_deg = click.option(
    "--max-residual-deg", type=FiniteFloatRange(min=0, min_open=True), default=AverageOptions.max_residual_deg,
    show_default=True, help="Edges further than this from the averaged rotations are filtered as outliers.")
gt = click.option(
    "--gt", "gt_path", type=click.Path(path_type=Path), default=None,
    help="Ground truth (Strecha folder, sfm_data.json or COLMAP model): writes OUT/eval/report.{json,html}.")
jobs = click.option(
    "--jobs", type=click.IntRange(min=1), default=None,
    callback=lambda ctx, param, value: _usable_cpus() if value is None else value,
    help="Processes for scene identification and TRRM (forked, Linux; default: the usable CPUs). The numbers do "
         "not depend on it. Both stay in one process while images are being decoded for the point colours (a fork "
         "is unsafe with a thread running).")
