"""`rotonly eval --gt GT ESTIMATE -o REPORT_DIR [--json]`: compare an estimate to ground truth."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from rotonly_cli.scene.types import SfMScene

logger = logging.getLogger(__name__)


def load_scene(path: str | Path, role: str) -> SfMScene:
    """Read GT or estimate (``role`` "gt" or "estimate"; a Strecha folder is GT only)."""
    from rotonly_cli.io.detect import read_scene

    return read_scene(path, field="--gt" if role == "gt" else "ESTIMATE", ground_truth=role == "gt")


@click.command("eval")
@click.option("--gt", "gt_path", required=True, type=click.Path(path_type=Path),
              help="Ground truth: Strecha folder (<scene>/ or gt_dense_cameras/), sfm_data.json or COLMAP model.")
@click.argument("estimate_path", metavar="ESTIMATE", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(path_type=Path),
              help="Report folder: report.json, report.html and PNG figures (replaced atomically).")
@click.option("--json", "as_json", is_flag=True, help="Print report.json to stdout (the table goes to stderr).")
def command(gt_path: Path, estimate_path: Path, out_dir: Path, as_json: bool) -> None:
    """Compare ESTIMATE to ground truth, openMVG_main_evalQuality-style, matching images by name.

    Reports the paper's geodesic rotation error after the best global rotation, the relative
    rotation error over all pairs, the centre error after a similarity, and evalQuality's own
    numbers (trace/3 angle, distance residuals).
    """
    from rotonly_cli.evaluation.quality import evaluate, unmatched_warning
    from rotonly_cli.evaluation.report import format_table, write_report

    gt = load_scene(gt_path, "gt")
    estimate = load_scene(estimate_path, "estimate")
    report = evaluate(gt, estimate)
    report.gt_path, report.estimate_path = str(gt_path), str(estimate_path)
    write_report(report, out_dir)
    click.echo(format_table(report), err=as_json)
    click.echo(f"report: {out_dir / 'report.html'}", err=as_json)
    warning = unmatched_warning(report.to_dict())
    if warning:
        click.echo(f"warning: {warning}", err=True)
    if as_json:
        click.echo(json.dumps(report.to_dict(), indent=2))
