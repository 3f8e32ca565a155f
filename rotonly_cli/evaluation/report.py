"""Write an evaluation (``QualityReport``) as ``report.json`` + ``report.html`` + PNG figures.

The directory is written atomically: everything goes to a temporary sibling directory that is
renamed onto ``out_dir`` at the end, so a failure leaves nothing behind.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path

import numpy as np

from rotonly_cli.evaluation.quality import QualityReport, Stats
from rotonly_cli.io.atomic import check_replaceable, staging_dir

FIGURES = {
    "per_camera_rotation.png": "Per-camera rotation error",
    "per_camera_position.png": "Per-camera position error",
    "cumulative_errors.png": "Cumulative error curves",
    "top_view.png": "Camera centres, top view",
}


#: per-camera rows of report.html shown before the rest is collapsed
SHOWN_CAMERAS = 50
OUTPUT_FILES = frozenset({"report.json", "report.html", *FIGURES})


def _fmt(value: float | None, digits: int = 6) -> str:
    return "n/a" if value is None else f"{value:.{digits}g}"


def summary_rows(report: QualityReport) -> list[tuple[str, Stats | None, str]]:
    """(metric, stats, unit) rows shared by the text table and the HTML table."""
    rows = [
        ("rotation error (geodesic, L2-aligned)", report.rotation_error_deg, "deg"),
        ("relative rotation error (all pairs)", report.relative_rotation_error_deg, "deg"),
        ("position error (similarity-aligned)", report.position_error, "GT units"),
    ]
    if report.evalquality is not None:
        rows += [
            ("evalQuality angular residual (trace/3)", report.evalquality.angular_residual_deg, "deg"),
            ("evalQuality distance residual", report.evalquality.distance_residual, "GT units"),
        ]
    return rows


def format_table(report: QualityReport) -> str:
    """Plain-text summary printed by ``rotonly eval``."""
    head = (f"cameras: GT {report.num_gt}, estimated {report.num_estimated}, matched {report.num_matched}"
            + (f", missing {len(report.missing_in_estimate)}" if report.missing_in_estimate else ""))
    rows = summary_rows(report)
    width = max(len(name) for name, _, _ in rows)
    lines = [head, f"{'metric':<{width}}  {'min':>11} {'mean':>11} {'median':>11} {'max':>11}  unit"]
    for name, stats, unit in rows:
        values = ["n/a"] * 4 if stats is None else [_fmt(v) for v in (stats.min, stats.mean, stats.median, stats.max)]
        lines.append(f"{name:<{width}}  " + " ".join(f"{v:>11}" for v in values) + f"  {unit}")
    for note in report.notes:
        lines.append(f"note: {note}")
    return "\n".join(lines)


def _cumulative(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step curve (x, fraction <= x) starting at (0, 0)."""
    v = np.sort(np.asarray(values, dtype=float))
    return np.concatenate([[0.0], v]), np.arange(v.size + 1) / max(v.size, 1)


def _make_figures(report: QualityReport, directory: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = report.per_camera
    names = [c.name for c in cams]
    x = np.arange(len(cams))
    label_step = max(1, len(cams) // 40)  # keep tick labels readable on big collections
    fig_width = min(16.0, max(6.0, 0.35 * len(cams) + 2.0))

    def _bars(values: list[list[float] | None], labels: list[str], ylabel: str, title: str, path: Path) -> None:
        fig, ax = plt.subplots(figsize=(fig_width, 4.0), dpi=110)
        present = [(v, lab) for v, lab in zip(values, labels) if v is not None]
        width = 0.8 / max(1, len(present))
        for k, (v, lab) in enumerate(present):
            if len(cams) <= 150:
                ax.bar(x + (k - (len(present) - 1) / 2) * width, v, width=width, label=lab)
            else:  # thousands of bars are slow to draw and unreadable: markers instead
                ax.plot(x, v, ".", markersize=3, label=lab)
        if not present:
            ax.text(0.5, 0.5, "not available (see notes)", ha="center", va="center", transform=ax.transAxes)
        ax.set_xticks(x[::label_step])
        ax.set_xticklabels(names[::label_step], rotation=60, ha="right", fontsize=8)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
        if len(present) > 1:
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)

    geodesic = [c.rotation_error_deg for c in cams]
    trace3 = None if report.evalquality is None else report.evalquality.rotation_angular_residuals
    _bars([geodesic, trace3], ["geodesic, L2-aligned (paper)", "evalQuality trace/3"],
          "rotation error [deg]", "Per-camera rotation error", directory / "per_camera_rotation.png")
    position = None if report.position_error is None else [c.position_error for c in cams]
    _bars([position], ["after similarity"], "position error [GT units]", "Per-camera position error (after similarity)",
          directory / "per_camera_position.png")

    # cumulative curves: fraction of cameras (pairs) with error <= x
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.0), dpi=110)
    curves = [("camera rotation (geodesic)", np.array(geodesic))]
    if trace3 is not None:
        curves.append(("camera rotation (evalQuality trace/3)", np.array(trace3)))
    for label, values in curves:
        axes[0].step(*_cumulative(values), where="post", label=label)
    axes[0].set_xlabel("rotation error [deg]")
    axes[0].set_ylabel("fraction of cameras")
    axes[0].set_title("Cumulative rotation error")
    axes[0].grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if position is not None:
        axes[1].step(*_cumulative(np.array(position)), where="post", color="C2")
        axes[1].set_title("Cumulative position error")
    else:
        axes[1].text(0.5, 0.5, "position error not available", ha="center", va="center", transform=axes[1].transAxes)
        axes[1].set_title("Cumulative position error")
    axes[1].set_xlabel("position error [GT units]")
    axes[1].set_ylabel("fraction of cameras")
    axes[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(directory / "cumulative_errors.png")
    plt.close(fig)

    # top view: drop the GT axis along which the centres spread least (the "up" axis of most scenes)
    centers_gt = np.array([c.center_gt for c in cams])
    spread = centers_gt.std(axis=0) if len(cams) > 1 else np.ones(3)
    keep = np.sort(np.argsort(spread)[1:])
    axis_names = "XYZ"
    fig, ax = plt.subplots(figsize=(6.5, 6.0), dpi=110)
    ax.scatter(centers_gt[:, keep[0]], centers_gt[:, keep[1]], s=40, marker="o", facecolors="none",
               edgecolors="C0", label="GT")
    if cams and cams[0].center_estimate_aligned is not None:
        aligned = np.array([c.center_estimate_aligned for c in cams])
        ax.scatter(aligned[:, keep[0]], aligned[:, keep[1]], s=14, marker="x", color="C3", label="estimate (aligned)")
        # errors are often far below the scene size: draw them magnified so they can be seen
        extent = float(np.ptp(centers_gt[:, keep], axis=0).max()) if len(cams) > 1 else 1.0
        largest = float(np.linalg.norm((aligned - centers_gt)[:, keep], axis=1).max())
        gain = max(1.0, 10.0 ** np.floor(np.log10(0.05 * extent / largest))) if largest > 0 else 1.0
        tips = centers_gt + gain * (aligned - centers_gt)
        for g, e in zip(centers_gt, tips):
            ax.plot([g[keep[0]], e[keep[0]]], [g[keep[1]], e[keep[1]]], color="C3", lw=1.0)
        ax.plot([], [], color="C3", lw=1.0, label=f"error x{gain:g}")
        title = "Camera centres, top view (estimate aligned by similarity)"
    else:
        title = "GT camera centres, top view (no estimated centres to align)"
    if len(cams) <= 40:
        for c, g in zip(cams, centers_gt):
            ax.annotate(c.name, (g[keep[0]], g[keep[1]]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel(f"GT {axis_names[keep[0]]}")
    ax.set_ylabel(f"GT {axis_names[keep[1]]}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.margins(0.08)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(directory / "top_view.png")
    plt.close(fig)


def _html(report: QualityReport) -> str:
    e = html.escape
    rows = []
    for name, stats, unit in summary_rows(report):
        cells = ["n/a"] * 4 if stats is None else [_fmt(v) for v in (stats.min, stats.mean, stats.median, stats.max)]
        rows.append(f"<tr><td>{e(name)}</td>" + "".join(f"<td>{c}</td>" for c in cells) + f"<td>{e(unit)}</td></tr>")
    camera_rows = []
    # worst first; the first SHOWN_CAMERAS rows shown, the rest collapsed (10 000 cameras: ~1 MB)
    for c in sorted(report.per_camera, key=lambda c: -c.rotation_error_deg):
        camera_rows.append(
            f"<tr><td>{e(c.name)}</td><td>{_fmt(c.rotation_error_deg)}</td><td>{_fmt(c.position_error)}</td>"
            f"<td>{_fmt(c.evalquality_angular_residual_deg)}</td><td>{_fmt(c.evalquality_distance_residual)}</td></tr>")
    camera_header = ("<tr><th>image</th><th>rotation error, geodesic [deg]</th><th>position error [GT]</th>"
                     "<th>evalQuality angle, acos(trace/3) [deg]</th><th>evalQuality distance [GT]</th></tr>")
    cameras = f"<table>{camera_header}\n{chr(10).join(camera_rows[:SHOWN_CAMERAS])}\n</table>"
    if len(camera_rows) > SHOWN_CAMERAS:
        cameras += (f'<details id="per-camera-rest"><summary>the other {len(camera_rows) - SHOWN_CAMERAS} cameras '
                    f"(worst first; all in report.json)</summary><table>{camera_header}\n"
                    f"{chr(10).join(camera_rows[SHOWN_CAMERAS:])}\n</table></details>")
    figures = "\n".join(f'<figure><img src="{f}" alt="{e(t)}"><figcaption>{e(t)}</figcaption></figure>'
                        for f, t in FIGURES.items())
    notes = "".join(f"<li>{e(n)}</li>" for n in report.notes)
    title = "/".join(Path(report.estimate_path).parts[-2:]) or "estimate vs ground truth"
    missing = ", ".join(report.missing_in_estimate) or "none"
    extra = ", ".join(report.not_in_gt) or "none"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>rotonly eval: {e(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; max-width: 1200px; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }}
td:first-child, th:first-child {{ text-align: left; }}
th {{ background: #eee; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; }}
code {{ background: #f4f4f4; padding: 0 0.2em; }}
</style></head><body>
<h1>rotonly eval: estimate vs ground truth</h1>
<p>Ground truth: <code>{e(report.gt_path)}</code><br>Estimate: <code>{e(report.estimate_path)}</code></p>
<p>Cameras: GT {report.num_gt}, estimated {report.num_estimated}, matched by image name {report.num_matched}.<br>
GT images without an estimated pose: {e(missing)}.<br>Estimated images not in the GT: {e(extra)}.</p>
<h2>Summary</h2>
<table><tr><th>metric</th><th>min</th><th>mean</th><th>median</th><th>max</th><th>unit</th></tr>
{chr(10).join(rows)}
</table>
<p>Rotation error: geodesic angle of R_gt<sup>T</sup> R_est S<sup>T</sup> after the best single global rotation S
(chordal L2 mean projected to SO(3)); the paper's metric. evalQuality rows reproduce
<code>openMVG_main_evalQuality</code>: Umeyama similarity on camera centres, angular residual
acos(clamp(trace/3)) (not a geodesic angle). Median convention: {e(report.median_convention)}.</p>
{'<ul>' + notes + '</ul>' if notes else ''}
<h2>Figures</h2>
{figures}
<h2>Per camera (worst rotation error first)</h2>
{cameras}
</body></html>
"""


def write_report(report: QualityReport, out_dir: str | os.PathLike) -> Path:
    """Write report.json, report.html and the PNGs into ``out_dir`` (replaced atomically)."""
    out_dir = Path(out_dir)
    check_replaceable(out_dir, OUTPUT_FILES, "an eval report")
    with staging_dir(out_dir) as tmp_dir:
        (tmp_dir / "report.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
        _make_figures(report, tmp_dir)
        (tmp_dir / "report.html").write_text(_html(report))
    return out_dir
