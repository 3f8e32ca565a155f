"""`rotonly eval --gt GT ESTIMATE -o REPORT_DIR [--json]`: compare an estimate to ground truth."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.scene.types import SfMScene

logger = logging.getLogger(__name__)


def _is_colmap_model(directory: Path) -> bool:
    return any((directory / f"cameras.{ext}").is_file() and (directory / f"images.{ext}").is_file()
               for ext in ("bin", "txt"))


def _reader(module: str, name: str):
    """Readers are imported lazily: the CLI loads fast and only needs the format it reads."""
    import importlib

    try:
        return getattr(importlib.import_module(f"rotonly_cli.io.{module}"), name)
    except (ModuleNotFoundError, AttributeError) as exc:
        raise AlgorithmError(f"reader rotonly_cli.io.{module}.{name} is not available: {exc}") from exc


def load_scene(path: str | Path, role: str) -> SfMScene:
    """Read GT or estimate: a Strecha folder (GT only), an OpenMVG sfm_data file or a COLMAP model.

    ``role`` is "gt" or "estimate" (a Strecha folder is accepted as GT only).
    """
    path = Path(path)
    option = "--gt" if role == "gt" else "ESTIMATE"
    if not path.exists():
        raise InputError("does not exist", path=str(path), field=option)
    if path.is_file():
        if path.suffix.lower() != ".json":
            raise InputError("expected an OpenMVG sfm_data .json file or a folder", path=str(path), field=option)
        return _reader("openmvg", "read_sfm_data")(str(path))
    if role == "gt" and ((path / "gt_dense_cameras").is_dir() or any(path.glob("*.camera"))):
        return _reader("strecha", "read_ground_truth")(str(path))
    if _is_colmap_model(path):
        return _reader("colmap", "read_model")(str(path))
    if (path / "sfm_data.json").is_file():  # a `rotonly run` output folder
        return _reader("openmvg", "read_sfm_data")(str(path / "sfm_data.json"))
    if (path / "sparse").is_dir() and _is_colmap_model(path / "sparse"):
        return _reader("colmap", "read_model")(str(path / "sparse"))
    expected = "gt_dense_cameras/, *.camera, " if role == "gt" else ""
    raise InputError(f"folder holds none of {expected}sfm_data.json, a COLMAP model (cameras/images .bin|.txt)",
                     path=str(path), field=option)


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
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.evaluation.report import format_table, write_report

    gt = load_scene(gt_path, "gt")
    estimate = load_scene(estimate_path, "estimate")
    report = evaluate(gt, estimate)
    report.gt_path, report.estimate_path = str(gt_path), str(estimate_path)
    write_report(report, out_dir)
    click.echo(format_table(report), err=as_json)
    click.echo(f"report: {out_dir / 'report.html'}", err=as_json)
    if as_json:
        click.echo(json.dumps(report.to_dict(), indent=2))
