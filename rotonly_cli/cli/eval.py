"""`rotonly eval --gt GT ESTIMATE -o REPORT_DIR [--json]`: compare an estimate to ground truth,
and with limits (``--max-rotation-deg``, ``--max-position``, ``--min-registered``,
``--baseline``) fail with exit code 3 when accuracy regressed (evaluation/gate.py)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from rotonly_cli.cli.options import FiniteFloatRange
from rotonly_cli.scene.types import SfMScene

logger = logging.getLogger(__name__)

#: eval's --help ends with its exit codes, 3 among them
EPILOG = """\b
Exit codes: 0 success (every limit held); 1 no result possible;
2 bad input or usage (one line names the file and the field; nothing is written);
3 accuracy regression: a limit was crossed (one line names each such metric, its
value and the limit; the report is written).
In CI: rotonly eval --gt GT OUT -o EVAL --max-rotation-deg 0.05 --baseline BASE/report.json"""


def load_scene(path: str | Path, role: str) -> SfMScene:
    """Read GT or estimate (``role`` "gt" or "estimate"; a Strecha folder is GT only). Of the
    ground truth only its poses (all the evaluation compares); the estimate whole, so that a
    broken file is refused."""
    from rotonly_cli.io.detect import read_scene

    return read_scene(path, field="--gt" if role == "gt" else "ESTIMATE", ground_truth=role == "gt",
                      poses_only=role == "gt")


@click.command("eval", epilog=EPILOG)
@click.option("--gt", "gt_path", required=True, type=click.Path(path_type=Path),
              help="Ground truth: Strecha folder (<scene>/ or gt_dense_cameras/), sfm_data.json or COLMAP model.")
@click.argument("estimate_path", metavar="ESTIMATE", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path),
              help="Report folder: report.json, report.html and PNG figures (replaced atomically).")
@click.option("--json", "as_json", is_flag=True, help="Print report.json to stdout (the table goes to stderr).")
@click.option("--max-rotation-deg", type=FiniteFloatRange(min=0), default=None,
              help="Exit 3 when the mean geodesic rotation error (deg) is above this.")
@click.option("--max-position", type=FiniteFloatRange(min=0), default=None,
              help="Exit 3 when the mean centre error after the similarity (GT units) is above this, or cannot "
                   "be computed.")
@click.option("--min-registered", type=click.IntRange(min=0), default=None,
              help="Exit 3 when fewer GT cameras than this have an estimated pose.")
@click.option("--baseline", "baseline_path", type=click.Path(path_type=Path), default=None,
              help="An earlier report.json (or its folder, or a run's OUT with eval/): exit 3 when a mean error "
                   "grew by more than --tolerance or fewer GT cameras have a pose.")
@click.option("--tolerance", default=None, metavar="SHARE",
              help="With --baseline: the growth allowed to the mean errors, as 10% or 0.1.  [default: 10%]")
def command(gt_path: Path, estimate_path: Path, out_dir: Path, as_json: bool, max_rotation_deg: float | None,
            max_position: float | None, min_registered: int | None, baseline_path: Path | None,
            tolerance: str | None) -> None:
    """Compare ESTIMATE to ground truth, openMVG_main_evalQuality-style, matching images by name.

    Reports the paper's geodesic rotation error after the best global rotation, the relative
    rotation error over all pairs, the centre error after a similarity, and evalQuality's own
    numbers (trace/3 angle, distance residuals). With limits it is a regression gate: a crossed
    limit exits with code 3 after writing the report.
    """
    from rotonly_cli.evaluation import gate
    from rotonly_cli.evaluation.quality import evaluate, unmatched_warning
    from rotonly_cli.evaluation.report import format_table, write_report

    if tolerance is not None and baseline_path is None:
        raise click.UsageError("--tolerance needs --baseline")
    share = gate.DEFAULT_TOLERANCE if tolerance is None else gate.parse_tolerance(tolerance)
    baseline = None if baseline_path is None else gate.read_baseline(baseline_path)
    gt = load_scene(gt_path, "gt")
    estimate = load_scene(estimate_path, "estimate")
    report = evaluate(gt, estimate)
    report.gt_path, report.estimate_path = str(gt_path), str(estimate_path)
    write_report(report, out_dir)
    click.echo(format_table(report), err=as_json)
    click.echo(f"report: {out_dir / 'report.html'}", err=as_json)
    data = report.to_dict()
    warning = unmatched_warning(data)
    if warning:
        click.echo(f"warning: {warning}", err=True)
    if as_json:
        click.echo(json.dumps(data, indent=2))
    found = gate.checks(data, max_rotation_deg, max_position, min_registered, baseline, share)
    gate.enforce(found)
    if found:
        click.echo(f"limits held: {'; '.join(check.line() for check in found)}", err=True)
