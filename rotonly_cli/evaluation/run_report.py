"""``OUT/report.html``: what a run did, on every run, in one self-contained page.

Written with the workspace (``rotonly run``, ``rotonly identify`` and the stage commands) from
the run's ``reports/*.json`` as written (so its numbers are theirs, and keys added to a report
later appear without code here), the view graph and the output scene: a summary, the time
per stage, the intrinsics before and after, reprojection errors and observation counts per
image, histograms of the residuals and track lengths, the view graph with its filtered edges
coloured by reason, a top view of the cameras, the ground-truth comparison with ``--gt``, and
every stage report. Figures are SVG (evaluation/svg.py) or the eval PNGs, embedded as data URIs.

Every number taken from a report carries ``data-source="<report>.<key>[.<key>...]"`` (list
items by index), which is how the tests compare the page with ``reports/*.json``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from html import escape
from pathlib import Path

import numpy as np

from rotonly_cli.evaluation import svg
from rotonly_cli.evaluation.run_figures import (  # noqa: F401 - top_view_axes: re-exported
    figure,
    per_view_figures,
    residual_histogram,
    top_view_axes,
    top_view_figure,
    track_histogram,
    view_graph_figure,
)
from rotonly_cli.scene.types import Intrinsics, SfMScene
from rotonly_cli.version import __version__

REPORT_FILE = "report.html"
#: list items shown of a report value (the JSON file has them all)
MAX_LIST_ITEMS = 24
MAX_TABLE_ROWS = 300
#: per-image rows shown before the rest is collapsed
SHOWN_ROWS = 50


# ============================================================================ statistics (reports/export.json)

@dataclass
class StructureStatistics:
    """Reprojection errors and observation counts of an output scene. ``report`` is
    reports/export.json's body; ``residuals_px`` every observation's error (for the histogram)."""

    report: dict
    residuals_px: np.ndarray


def _focal_px(intrinsics: Intrinsics | None) -> float:
    return float("nan") if intrinsics is None else intrinsics.focal_px


def _stats(values: np.ndarray) -> dict | None:
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    return {"mean": float(values.mean()), "median": float(np.median(values)), "max": float(values.max()),
            "rmse": float(np.sqrt(np.mean(values ** 2)))}


def structure_statistics(scene: SfMScene, view_ids: list[int]) -> StructureStatistics:
    """Per observation the distance between the keypoint and its point's projection, in
    pixels of the undistorted image (normalized residual x focal length), and per view the
    number of observations, for the views ``view_ids``."""
    residuals = np.zeros(0)
    per_view_errors: dict[int, np.ndarray] = {}
    track_lengths = np.zeros(0, dtype=np.int64)
    structure = scene.structure
    if structure is not None and len(structure.points):
        track_lengths, view_feature = structure.flat_observations()
        track_lengths = np.asarray(track_lengths, dtype=np.int64)
        point_of = np.repeat(np.arange(len(track_lengths)), track_lengths)
        residuals = np.full(len(view_feature), np.nan)
        points = np.asarray(structure.points, dtype=float)
        by_view = np.argsort(view_feature[:, 0], kind="stable")  # observations grouped by view
        views, first = np.unique(view_feature[by_view, 0], return_index=True)
        for view_id, rows in zip(views.tolist(), np.split(by_view, first[1:])):
            pose, observed = scene.poses.get(view_id), scene.normalized.get(view_id)
            if pose is None or observed is None:
                continue
            x_cam = (points[point_of[rows]] - pose.center) @ np.asarray(pose.R_cam_from_world).T
            with np.errstate(all="ignore"):
                projected = x_cam[:, :2] / x_cam[:, 2:3]
            error = np.linalg.norm(projected - observed[view_feature[rows, 1]], axis=1)
            view = scene.views.get(view_id)
            residuals[rows] = error * _focal_px(scene.intrinsics.get(view.intrinsics_id) if view else None)
            per_view_errors[view_id] = residuals[rows]
    per_view = []
    for view_id in view_ids:
        errors = per_view_errors.get(view_id, np.zeros(0))
        stats = _stats(errors)
        per_view.append({"id": int(view_id), "name": scene.views[view_id].name if view_id in scene.views else "",
                         "registered": view_id in scene.poses, "num_observations": int(errors.size),
                         "reprojection_error_px": None if stats is None else
                         {k: stats[k] for k in ("mean", "median", "max")}})
    lengths, counts = np.unique(track_lengths, return_counts=True)
    report = {"num_views": len(view_ids), "num_registered": sum(1 for v in view_ids if v in scene.poses),
              "num_points": int(len(track_lengths)), "num_observations": int(residuals.size),
              "reprojection_error_px": _stats(residuals),
              "track_lengths": {str(int(n)): int(c) for n, c in zip(lengths, counts)},
              "root_path": scene.root_path, "per_view": per_view}
    return StructureStatistics(report, residuals)


# ============================================================================ reading the reports

def read_reports(reports_dir: Path, stages_done: list[str]) -> dict[str, dict]:
    """reports/<name>.json as written, in chain order (stages.STAGES, then export): the
    stages done (a stage command leaves the later stages' files of an earlier run: stale, left
    out), export only after triangulation, any other report, ``run`` last."""
    found = {path.stem: path for path in sorted(reports_dir.glob("*.json"))} if reports_dir.is_dir() else {}
    from rotonly_cli.stages import STAGES

    def current(name: str) -> bool:
        if name in STAGES:
            return name in stages_done
        return name != "export" or stages_done[-1:] == ["triangulate"]

    order = (*STAGES, "export")
    names = [n for n in order if n in found] + sorted(set(found) - set(order) - {"run"})
    names += ["run"] if "run" in found else []
    reports = {}
    for name in names:
        if current(name):
            try:
                reports[name] = json.loads(found[name].read_text())
            except (OSError, ValueError):
                continue
    return reports


# ============================================================================ HTML pieces

def _fmt(value) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _get(reports: dict, path: str):
    """The value at ``report.key.key...`` (list items by index), None when absent."""
    value = reports
    for key in path.split("."):
        if isinstance(value, dict):
            value = value.get(key)
        elif isinstance(value, list) and key.isdigit() and int(key) < len(value):
            value = value[int(key)]
        else:
            return None
    return value


def _num(reports: dict, path: str, suffix: str = "") -> str:
    """A report number as a table cell's content, tagged with where it comes from (times,
    ``*time_s``, in seconds to the millisecond)."""
    value = _get(reports, path)
    if value is None or isinstance(value, (dict, list)):
        return "–"
    return f'<span data-source="{escape(path)}">{escape(_shown(value, path))}</span>{suffix}'


def _shown(value, path: str) -> str:
    """:func:`_fmt`, but times (``*time_s``) in seconds to the millisecond: a stage's 3e-05 s
    reads 0.000, not 3e-05."""
    if path.endswith("time_s") and isinstance(value, (int, float)) and not isinstance(value, bool):
        return f"{value:.3f}"
    return _fmt(value)


def _table(header: list[str] | None, rows: list[list[str]], cls: str = "") -> str:
    head = "" if header is None else "<tr>" + "".join(f"<th>{escape(h)}</th>" for h in header) + "</tr>"
    body = "\n".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}">{head}\n{body}\n</table>'


def _value_html(value, path: str) -> str:
    """A report value of any shape: scalars tagged with their path, dicts as nested tables,
    lists of scalars inline (shortened), lists of dicts as tables."""
    if isinstance(value, dict):
        if not value:
            return "{}"
        rows = [[escape(str(k)), _value_html(v, f"{path}.{k}")] for k, v in value.items()]
        return _table(["key", "value"], rows, "nested")
    if isinstance(value, list):
        if value and all(isinstance(v, dict) for v in value):
            keys = list(dict.fromkeys(k for v in value for k in v))
            rows = [[_value_html(v.get(k), f"{path}.{i}.{k}") for k in keys]
                    for i, v in enumerate(value[:MAX_TABLE_ROWS])]
            more = (f"<p>… {len(value) - MAX_TABLE_ROWS} more rows in the JSON file</p>"
                    if len(value) > MAX_TABLE_ROWS else "")
            return _table(keys, rows, "nested") + more
        shown = ", ".join(_value_html(v, f"{path}.{i}") for i, v in enumerate(value[:MAX_LIST_ITEMS]))
        more = f", … ({len(value)} items)" if len(value) > MAX_LIST_ITEMS else ""
        return f"[{shown}{more}]"
    return f'<span data-source="{escape(path)}">{escape(_shown(value, path))}</span>'


# ============================================================================ sections

def _summary(reports: dict, graph) -> str:
    counts = graph.counts()
    reasons = counts.get("filtered_by_reason", {})
    rows = [
        ["views registered", _num(reports, "run.num_registered") + " of " + _num(reports, "run.num_views")
         if "num_registered" in reports.get("run", {}) else "– of " + _num(reports, "load.num_views")],
        ["points", _num(reports, "run.num_points")],
        ["observations", _num(reports, "export.num_observations")],
        ["edges active", _num(reports, "run.num_active_edges") + " of " + _num(reports, "load.num_pairs")],
        ["edges filtered", ", ".join(f"{escape(r)}: {n}" for r, n in sorted(reasons.items())) or "none"],
        ["views outside the largest component", escape(", ".join(map(str, counts["unregistered_views"]))) or "none"],
        ["models (connected parts of the view graph)", _components(reports)],
        ["reprojection error [px]", "median " + _num(reports, "export.reprojection_error_px.median") + ", mean "
         + _num(reports, "export.reprojection_error_px.mean") + ", RMSE "
         + _num(reports, "export.reprojection_error_px.rmse") + ", max "
         + _num(reports, "export.reprojection_error_px.max")],
        ["pairs' rotations about the global ones [deg]", "median " + _num(reports, "run.pair_residual_deg_median")],
        ["rotation error vs ground truth, geodesic [deg]", "mean " + _num(reports, "run.rotation_error_deg.mean")
         + ", median " + _num(reports, "run.rotation_error_deg.median")
         if _get(reports, "run.rotation_error_deg") else "no --gt"],
        ["total time", _num(reports, "run.time_s", " s")],
    ]
    return _table(None, rows, "summary")


def _components(reports: dict) -> str:
    """The models written (sparse/ and the other components' sparse/<k>/) and the parts not
    written, from reports/run.json's ``components``."""
    lines = []
    for k, part in enumerate(_get(reports, "run.components") or []):
        base = f"run.components.{k}"
        if part.get("model"):
            lines.append(f"<code>{escape(part['model'])}/</code>, <code>{escape(part['sfm_data'])}</code>: "
                         + _num(reports, f"{base}.num_registered") + " of " + _num(reports, f"{base}.num_views")
                         + " views, " + _num(reports, f"{base}.num_points") + " points")
        else:
            views = ", ".join(map(str, part.get("views", [])[:MAX_LIST_ITEMS]))
            lines.append(f"not written: views {escape(views)} ({_num(reports, f'{base}.reason')})")
    return "<br>".join(lines) or "–"


def _timings(reports: dict) -> str:
    rows = []
    total = _get(reports, "run.time_s") or 0.0
    resources = reports.get("resources", {})
    for name, report in reports.items():
        if name == "run" or not isinstance(report.get("time_s"), (int, float)):
            continue
        share = 100.0 * report["time_s"] / total if total else 0.0
        # the process's peak resident memory by the stage's end (reports/resources.json)
        memory = _num(reports, f"resources.{name}.peak_rss_mb") if name in resources else "–"
        rows.append([escape(name), _num(reports, f"{name}.time_s"),
                     f'<span class="bar" style="width:{min(share, 100):.0f}%"></span> {share:.0f} %', memory])
    if "time_s" in reports.get("run", {}):
        rows.append(["<b>run (total, with reading and writing)</b>", _num(reports, "run.time_s"), "", ""])
    return _table(["stage", "time [s]", "share of the run", "peak memory [MB]"], rows, "timings")


def _intrinsics(before: dict, after: dict) -> str:
    ids = sorted(set(before) | set(after))
    if not ids:
        return "<p>No intrinsics.</p>"
    rows = []
    for k in ids:
        first, last = before.get(k), after.get(k)

        def cell(intrinsics: Intrinsics | None) -> str:
            if intrinsics is None:
                return "–"
            params = ", ".join(f"{p:.6g}" for p in np.asarray(intrinsics.params, dtype=float).ravel())
            return f"{escape(intrinsics.model)} {intrinsics.width}×{intrinsics.height}: {params}"

        changed = first is None or last is None or first.model != last.model or not np.array_equal(
            np.asarray(first.params, dtype=float), np.asarray(last.params, dtype=float))
        rows.append([str(k), cell(first), cell(last), "changed" if changed else "unchanged"])
    return _table(["camera", "before (input)", "after (written to sparse/)", ""], rows, "intrinsics")


def _per_view_table(reports: dict, evaluation: dict | None) -> str:
    """Per image: observations, reprojection errors and, with ``evaluation`` (OUT/eval/
    report.json), the errors against the ground truth. Worst first: by the geodesic rotation
    error with GT (images without one last), else by the median reprojection error
    (unregistered images first). The first SHOWN_ROWS rows are shown, the rest in a collapsed
    <details> (plain cells: 10 000 rows stay ~1.5 MB)."""
    per_view = _get(reports, "export.per_view") or []
    truth = {c.get("name"): c for c in (evaluation or {}).get("per_camera") or []}

    def worst_first(k: int):
        view = per_view[k]
        if evaluation is not None:
            error = (truth.get(view.get("name")) or {}).get("rotation_error_deg")
            return (error is None, -(error or 0.0), k)
        median = (view.get("reprojection_error_px") or {}).get("median")
        return (bool(view.get("registered")), -(median if median is not None else np.inf), k)

    order = sorted(range(len(per_view)), key=worst_first)
    header = ["image", "id", "registered", "observations", "median [px]", "mean [px]", "max [px]"]
    if evaluation is not None:
        header += ["rotation error, geodesic [deg]", "evalQuality angle, acos(trace/3) [deg]",
                   "position error [GT units]"]
    gt_keys = ("rotation_error_deg", "evalquality_angular_residual_deg", "position_error")

    def row(k: int, tagged: bool) -> list[str]:
        view, base = per_view[k], f"export.per_view.{k}"
        keys = ("id", "registered", "num_observations", "reprojection_error_px.median",
                "reprojection_error_px.mean", "reprojection_error_px.max")
        cells = [escape(view.get("name", ""))] + [_num(reports, f"{base}.{key}") if tagged
                                                  else escape(_fmt(_get(view, key))) for key in keys]
        if evaluation is not None:
            camera = truth.get(view.get("name")) or {}
            cells += [escape(_fmt(camera.get(key))) for key in gt_keys]
        return cells

    shown = _table(header, [row(k, True) for k in order[:SHOWN_ROWS]], "per-view")
    if len(order) <= SHOWN_ROWS:
        return shown
    rest = _table(header, [row(k, False) for k in order[SHOWN_ROWS:]], "per-view")
    return (shown + f'<details id="per-view-rest"><summary>the other {len(order) - SHOWN_ROWS} images (worst '
            f"first; all in reports/export.json)</summary>{rest}</details>")


def _filtered_edges(graph) -> str:
    filtered = [e for e in graph.edges if e.status != "active"]
    if not filtered:
        return "<p>No edge was filtered.</p>"
    def name(view_id: int) -> str:
        view = graph.views.get(view_id)
        return escape(f"{view_id} ({view.name})" if view is not None else str(view_id))

    rows = [[name(e.i), name(e.j), str(e.num_inliers), escape(e.reason)] for e in filtered[:MAX_TABLE_ROWS]]
    more = (f"<p>… {len(filtered) - MAX_TABLE_ROWS} more in view_graph.json</p>"
            if len(filtered) > MAX_TABLE_ROWS else "")
    return _table(["view i", "view j", "inliers", "reason"], rows, "edges") + more


def _evaluation(directory: Path) -> dict | None:
    """OUT/eval/report.json (the --gt comparison), None when absent or unreadable."""
    try:
        evaluation = json.loads((directory / "eval" / "report.json").read_text())
    except (OSError, ValueError):
        return None
    return evaluation if isinstance(evaluation, dict) else None


def _ground_truth(directory: Path, evaluation: dict | None) -> str:
    """The --gt comparison of OUT/eval/ (report.json and its PNG figures)."""
    if evaluation is None:
        return ""
    from rotonly_cli.evaluation.report import FIGURES

    eval_dir = directory / "eval"
    rows = []
    evalquality = evaluation.get("evalquality") or {}
    for stats, label in ((evaluation.get("rotation_error_deg"), "rotation error, geodesic [deg]"),
                         (evalquality.get("angular_residual_deg"), "evalQuality angular residual, acos(trace/3) [deg]"),
                         (evaluation.get("relative_rotation_error_deg"), "relative rotation error, geodesic [deg]"),
                         (evaluation.get("position_error"), "position error [GT units]")):
        if stats is not None or "geodesic" in label:
            stats = stats or {}
            rows.append([escape(label)] + [escape(_fmt(stats.get(k))) for k in ("min", "mean", "median", "max")])
    figures = []
    for name, caption in FIGURES.items():
        if (eval_dir / name).is_file():
            figures.append(figure(svg.png_data_uri((eval_dir / name).read_bytes()), caption,
                                  f"fig-gt-{Path(name).stem}"))
    head = (f"<p>Ground truth <code>{escape(str(evaluation.get('gt_path', '')))}</code>: "
            f"{escape(_fmt(evaluation.get('num_matched')))} of {escape(_fmt(evaluation.get('num_gt')))} cameras "
            f'matched by image name. Full report: <a href="eval/report.html">eval/report.html</a>.</p>')
    metrics = ("<p>Geodesic: the angle of R<sub>gt</sub><sup>T</sup> R<sub>est</sub> S<sup>T</sup> after the best "
               "global rotation S (the paper's metric). evalQuality: <code>openMVG_main_evalQuality</code>'s "
               "acos(trace/3) after its similarity on the centres, not a geodesic angle "
               "(about 0.816 of it for small errors).</p>")
    return ("<h2>Ground truth (--gt)</h2>" + head
            + _table(["metric", "min", "mean", "median", "max"], rows, "gt") + metrics + "\n".join(figures))


def _command(reports: dict) -> str:
    """The command line of the run (reports/run.json ``command``; absent for an API call) and
    its options, collapsed."""
    command = _get(reports, "run.command")
    options = _get(reports, "run.options")
    line = f"<p>Command: <code>{escape(command)}</code></p>" if command else ""
    return line + (f'<details id="options"><summary>options</summary>{_value_html(options, "run.options")}'
                   "</details>" if options else "")


def _warnings(reports: dict) -> str:
    """The run's warnings (the summary's, as the terminal and run.log show them), first on
    the page; "No warnings." when the run had none; empty before the summary has them."""
    warnings = _get(reports, "run.warnings")
    if not warnings:
        return '<p class="no-warnings" id="warnings">No warnings.</p>' if warnings is not None else ""
    items = "".join(f"<li>{escape(str(w))}</li>" for w in warnings)
    return f'<div class="warnings" id="warnings"><h2>Warnings</h2><ul>{items}</ul></div>'


# ============================================================================ page

STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1440px; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 0.6em 0; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.55em; text-align: right; vertical-align: top; }
td:first-child, th:first-child { text-align: left; }
th { background: #eee; }
table.summary td:first-child { font-weight: bold; }
table.nested { margin: 0; font-size: 0.92em; }
table.intrinsics td, table.nested td { text-align: left; }
figure { display: inline-block; margin: 0.6em 1.2em 0.6em 0; vertical-align: top; }
figcaption { font-size: 0.85em; color: #555; }
img { max-width: 100%; border: 1px solid #ddd; }
span.bar { display: inline-block; height: 0.7em; background: #1f77b4; vertical-align: middle; max-width: 12em; }
details { margin: 0.4em 0; } summary { cursor: pointer; font-weight: bold; }
code { background: #f4f4f4; padding: 0 0.2em; }
div.warnings { background: #fff4e5; border: 1px solid #f0a040; padding: 0 1em; margin: 1em 0; }
"""


def build_html(directory: Path, run, scene: SfMScene | None, statistics: StructureStatistics | None,
               stages_done: list[str]) -> str:
    reports = read_reports(directory / "reports", stages_done)
    load = reports.get("load", {})
    input_path = str(load.get("input", run.input_path))
    evaluation = _evaluation(directory) if run.options.gt and "triangulate" in stages_done else None
    parts = [f"<h1>rotonly report</h1><p>Input <code>{escape(input_path)}</code> "
             f"({escape(str(load.get('input_kind', run.input_kind)))}); stages done: "
             f"{escape(', '.join(stages_done))}; rotonly {escape(__version__)}.</p>", _command(reports),
             _warnings(reports), "<h2>Summary</h2>", _summary(reports, run.graph),
             "<h2>Time per stage</h2>", _timings(reports)]
    after = scene.intrinsics if scene is not None else run.scene.intrinsics
    parts += ["<h2>Intrinsics</h2>", _intrinsics(run.input_intrinsics or run.scene.intrinsics, after)]
    if "export" in reports:
        parts += ["<h2>Per image</h2>", *per_view_figures(reports["export"].get("per_view") or []),
                  _per_view_table(reports, evaluation)]
        histograms = [f for f in (residual_histogram(statistics.residuals_px) if statistics else None,
                                  track_histogram(reports["export"].get("track_lengths") or {})) if f]
        parts += ["<h2>Residuals and tracks</h2>", *histograms]
    parts += ["<h2>View graph</h2>", view_graph_figure(run.graph) or "", _filtered_edges(run.graph)]
    if scene is not None:
        top = top_view_figure(scene)
        parts += ["<h2>Cameras</h2>", top] if top else []
    parts.append(_ground_truth(directory, evaluation))
    parts.append("<h2>Stage reports</h2><p>Every number of <code>reports/&lt;stage&gt;.json</code>.</p>")
    for name, report in reports.items():
        parts.append(f'<details id="report-{escape(name)}"><summary>{escape(name)}</summary>'
                     f"{_value_html(report, name)}</details>")
    body = "\n".join(p for p in parts if p)
    title = "/".join(Path(input_path).parts[-2:])  # the input and its folder: what a tab or bookmark names
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>rotonly: {escape(title)}</title>'
            f"<style>{STYLE}</style></head><body>\n{body}\n</body></html>\n")


def write_run_report(directory: str | os.PathLike, run, scene: SfMScene | None,
                     statistics: StructureStatistics | None, stages_done: list[str]) -> Path:
    """``directory/report.html`` (atomically) for ``run`` after ``stages_done``; ``scene``: the
    output scene when the chain reached triangulation."""
    from rotonly_cli.io import atomic

    path = Path(directory) / REPORT_FILE
    page = build_html(Path(directory), run, scene, statistics, stages_done)
    # file names that are not UTF-8 (surrogate escapes) are shown backslash-escaped, as in run.log
    atomic.write_bytes(path, page.encode("utf-8", errors="backslashreplace"))
    return path
