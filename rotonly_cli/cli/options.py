"""Every click option used by more than one command, declared once; defaults come from
rotonly_cli/options/.

=====================  ==============================================================
option                 commands
=====================  ==============================================================
--matches-dir          run, identify, convert (OpenMVG input)
-M, --matches          run, identify, convert (OpenMVG input)
--image-path           run, identify, triangulate
--min-inliers          run, identify
--reestimate           run, identify
--ransac-max-error     run, identify, refine (simulated edge)
--seed (RANSAC)        run, identify
--consensus            run, identify
--max-residual-deg     run, average
--gt (GT_PATH)         run, triangulate
--jobs                 run, identify, refine, optimize, translate, reject, triangulate
--cluster              run, identify
--intrinsics           run, identify
--max-memory           run, identify
=====================  ==============================================================
"""

from __future__ import annotations

from pathlib import Path

import click

from rotonly_cli.options import (
    CONSENSUS_MODES,
    INTRINSICS_MODES,
    REESTIMATE_MODES,
    AverageOptions,
    Consensus,
    IntrinsicsOptions,
    LoadOptions,
)

#: `rotonly refine FILE.npz`: the 5-point RANSAC threshold (px) when --ransac-max-error is not given
SIMULATION_RANSAC_MAX_ERROR_PX = 2.0


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
matches_file = click.option(
    "-M", "--matches", "matches", type=click.Path(path_type=Path), default=None,
    help="OpenMVG input: the matches file, as OpenMVG's --match_file (a bare name is looked up in --matches-dir; "
         "default: the first of matches.e, matches.f, matches.putative .bin|.txt there).")
image_path = click.option(
    "--image-path", type=click.Path(path_type=Path), default=None,
    help="Images, for point colours (default: images/ beside a database, root_path of an OpenMVG project; "
         "missing images give grey points).")
min_inliers = click.option(
    "--min-inliers", type=click.IntRange(min=6), default=LoadOptions.min_inliers, show_default=True,
    help="Edges with fewer inlier matches are filtered.")
reestimate = click.option(
    "--reestimate", type=click.Choice(REESTIMATE_MODES), default=LoadOptions.reestimate.value, show_default=True,
    help="Which relative poses calibrated RANSAC re-estimates: all = every edge; auto = edges without an "
         "E-based stored pose (PLANAR/UNCALIBRATED/... or none stored), the others kept; none = stored poses "
         "only (edges without one filtered).")
ransac_max_error = click.option(
    "--ransac-max-error", type=FiniteFloatRange(min=0, min_open=True), default=LoadOptions.ransac_max_error_px,
    show_default=True, help="RANSAC inlier threshold in pixels for the relative poses (default: "
    f"{LoadOptions.inlier_threshold_sigmas:g} x the matches' noise sigma, measured on the input; refine FILE.npz: "
    f"{SIMULATION_RANSAC_MAX_ERROR_PX:g} px).")
seed = click.option("--seed", type=click.IntRange(0, 2 ** 31 - 1), default=LoadOptions.seed, show_default=True,
                    help="RANSAC seed (runs are deterministic).")
consensus = click.option(
    "--consensus", type=click.Choice(CONSENSUS_MODES), default=Consensus.AUTO.value, show_default=True,
    help=f"How each edge's inlier matches are settled: full = {LoadOptions.consensus_runs} seeded RANSAC runs, the "
         "matches all of them accept kept; fast = on edges of more than "
         f"{LoadOptions.agreement_min_matches} matches, two runs on {LoadOptions.agreement_max_matches} matches "
         "whose inliers agree are kept as they are (the relative poses of a large collection ~5x faster, less "
         f"robust on repeated structure); auto = fast from {LoadOptions.agreement_min_edges} pairs to "
         "re-estimate on, else full.")
intrinsics = click.option(
    "--intrinsics", type=click.Choice(INTRINSICS_MODES), default=IntrinsicsOptions.mode.value, show_default=True,
    help="Camera intrinsics: fixed = used as given; refine = every camera calibrated (focal from the view graph, "
         "then focal, principal point and radial terms from the reconstruction); auto = cameras the input marks as "
         "a guess (COLMAP prior_focal_length = 0), cameras whose reprojection error shows them wrong, and "
         "cameras whose principal point sits at the image centre (the front ends' default) where one "
         "adjustment moves it are calibrated, the others stay as given. Poses always come from the "
         "rotation-only stages.")
#: the load stage's options (`run` and `identify`)
load_options = _all(matches_dir, matches_file, image_path, min_inliers, reestimate, ransac_max_error, seed,
                    consensus, intrinsics)

max_residual_deg = click.option(
    "--max-residual-deg", type=FiniteFloatRange(min=0, min_open=True), default=AverageOptions.max_residual_deg,
    show_default=True, help="Edges further than this from the averaged rotations are filtered as outliers.")
gt = click.option(
    "--gt", type=click.Path(path_type=Path), default=None,
    help="Ground truth (Strecha folder, sfm_data.json or COLMAP model): writes OUT/eval/report.{json,html}.")
jobs = click.option(
    "--jobs", type=click.IntRange(min=1), default=None,
    callback=lambda ctx, param, value: _usable_cpus() if value is None else value,
    help=f"CPUs to use (default: the usable CPUs, {_usable_cpus()} here): threads for the RANSAC of relative "
         "poses, forked processes (Linux) for scene identification and TRRM, one per 20000 matches at most, and "
         "for GRRM and LiGT's robust rounds (two each) and writing sfm_data.json (a smaller input runs in one "
         "process; reports/refine.json, optimize.json and translate.json record how many ran). The numbers do "
         "not depend on it.")


def _cluster_address(ctx, param, value):
    """--cluster checked at once (options.cluster_address): a usage error, exit 2."""
    if value is None:
        return None
    from rotonly_cli.options import cluster_address

    try:
        cluster_address(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc).removeprefix("--cluster: ")) from None
    return value.strip()


cluster = click.option(
    "--cluster", metavar="ADDRESS", default=None, callback=_cluster_address,
    help="Run the per-pair and per-track work (RANSAC of the relative poses, scene identification, TRRM, the "
         "rejection's residuals, triangulation) on a Dask cluster: tcp://HOST:PORT attaches to a running `dask "
         "scheduler` (with `dask worker`s), local:N starts N single-threaded worker processes for this run. Needs "
         "the extra 'cluster' (pip install 'rotonly_cli[cluster]'). GRRM, the averaging and LiGT stay in this "
         "process (--jobs); the outputs are the same bytes. reports/run.json records the tasks and bytes sent.")
max_memory = click.option(
    "--max-memory", type=FiniteFloatRange(min=0, min_open=True), default=None, metavar="GB",
    help="Stop (exit 1, one line, OUT as it was) before a stage whose predicted peak memory is above this many GB "
         "(2^30 bytes) or above the memory available (MemAvailable + the run's own, within a cgroup or ulimit -v), "
         "which is the limit without this option. reports/run.json records the predictions and the limit.")
