"""The figures of ``OUT/report.html`` (evaluation/run_report.py): per image, residuals and
track lengths, the view graph, the cameras from above. SVG (evaluation/svg.py) as data URIs.

A collection of thousands of views keeps the page small: per-image bars become histograms over
the images, the view graph's views a ring with the unregistered ones marked and its active
edges a sample, the cameras from above a sample (the counts say so in the legends).
"""

from __future__ import annotations

from html import escape

import numpy as np

from rotonly_cli.evaluation import svg
from rotonly_cli.scene.types import SfMScene

TOP_VIEW_POINTS = 4000
#: above this many registered images the per-image bars become histograms over the images
MAX_BAR_IMAGES = 300
#: at most this many marks (views, cameras, edges of one kind) are drawn; beyond, one in k
MAX_MARKS = 1000


def figure(uri: str, caption: str, figure_id: str) -> str:
    return (f'<figure id="{figure_id}"><img src="{uri}" alt="{escape(caption)}">'
            f"<figcaption>{escape(caption)}</figcaption></figure>")


def per_view_figures(per_view: list[dict]) -> list[str]:
    registered = [v for v in per_view if v["registered"]]
    if not registered:
        return []
    median = np.array([(v["reprojection_error_px"] or {}).get("median", np.nan) for v in registered], dtype=float)
    mean = np.array([(v["reprojection_error_px"] or {}).get("mean", np.nan) for v in registered], dtype=float)
    counts = np.array([v["num_observations"] for v in registered], dtype=float)
    if len(registered) > MAX_BAR_IMAGES:
        return _per_view_histograms(median, counts)
    names = [v["name"] or str(v["id"]) for v in registered]
    x = np.arange(len(registered))
    width = int(min(1400, max(640, 60 + 18 * len(registered))))
    top = float(np.nanmax(np.concatenate([mean, median, [0.0]]))) or 1.0
    chart = svg.Chart(width, 360, (-0.6, len(registered) - 0.4), (0.0, 1.1 * top), categories=names,
                      title="Reprojection error per image", ylabel="pixels (undistorted)")
    chart.bars(x, median, width=0.4, offset=-0.2, color=svg.PALETTE[0], label="median")
    chart.bars(x, mean, width=0.4, offset=0.2, color=svg.PALETTE[1], label="mean")
    observations = svg.Chart(width, 340, (-0.6, len(registered) - 0.4), (0.0, 1.1 * max(counts.max(), 1.0)),
                             categories=names, title="Observations per image (3D points seen)", ylabel="observations")
    observations.bars(x, counts, color=svg.PALETTE[2])
    return [figure(svg.data_uri(chart.svg()), "Reprojection error per image (median, mean)", "fig-per-image-error"),
            figure(svg.data_uri(observations.svg()), "Observations per image", "fig-per-image-observations")]


def _per_view_histograms(median: np.ndarray, counts: np.ndarray) -> list[str]:
    """The per-image figures of a collection too large for a bar per image: how many images
    have each median reprojection error and each number of observations."""
    charts = []
    for values, title, xlabel, colour in (
            (median, "Median reprojection error of the images", "pixels (undistorted)", svg.PALETTE[0]),
            (counts, "Observations of the images (3D points seen)", "observations", svg.PALETTE[2])):
        values = values[np.isfinite(values)]
        upper = float(values.max()) if values.size else 1.0
        edges = np.linspace(0.0, upper or 1.0, 41)
        number, _ = np.histogram(values, bins=edges)
        chart = svg.Chart(640, 320, (0.0, edges[-1]), (0.0, 1.1 * max(number.max(), 1)),
                          title=f"{title}: {values.size} images", xlabel=xlabel, ylabel="images")
        chart.bars((edges[:-1] + edges[1:]) / 2, number, width=edges[1] - edges[0], color=colour)
        charts.append(chart)
    return [figure(svg.data_uri(charts[0].svg()), "Median reprojection error per image, histogram over the images",
                   "fig-per-image-error"),
            figure(svg.data_uri(charts[1].svg()), "Observations per image, histogram over the images",
                   "fig-per-image-observations")]


def residual_histogram(residuals: np.ndarray) -> str | None:
    residuals = residuals[np.isfinite(residuals)]
    if not residuals.size:
        return None
    upper = float(np.quantile(residuals, 0.99)) or float(residuals.max()) or 1.0
    edges = np.linspace(0.0, upper, 41)
    counts, _ = np.histogram(np.minimum(residuals, upper), bins=edges)
    chart = svg.Chart(640, 320, (0.0, upper), (0.0, 1.1 * counts.max()), title="Reprojection error of the observations",
                      xlabel=f"pixels (last bin: >= {upper:.3g}, the 99th percentile)", ylabel="observations")
    chart.bars((edges[:-1] + edges[1:]) / 2, counts, width=edges[1] - edges[0], color=svg.PALETTE[0])
    return figure(svg.data_uri(chart.svg()), "Histogram of the reprojection errors", "fig-residuals")


def track_histogram(track_lengths: dict) -> str | None:
    if not track_lengths:
        return None
    lengths = np.array([int(k) for k in track_lengths])
    counts = np.array([track_lengths[k] for k in track_lengths], dtype=float)
    chart = svg.Chart(640, 320, (lengths.min() - 0.6, lengths.max() + 0.6), (0.0, 1.1 * counts.max()),
                      title="Track lengths of the points", xlabel="views observing the point", ylabel="points")
    chart.bars(lengths, counts, color=svg.PALETTE[2])
    return figure(svg.data_uri(chart.svg()), "Histogram of the track lengths", "fig-track-lengths")


def view_graph_figure(graph) -> str | None:
    view_ids = graph.view_ids()
    if len(view_ids) < 2:
        return None
    angle = np.pi / 2 - 2 * np.pi * np.arange(len(view_ids)) / len(view_ids)
    position = {v: (np.cos(a), np.sin(a)) for v, a in zip(view_ids, angle)}
    chart = svg.Chart(720, 640, (-1.35, 1.35), (-1.25, 1.25), title="View graph: edges by status (filtered: reason)",
                      equal=True, axes=False, margins=(10, 10, 30, 10))
    groups: dict[str, list] = {}
    for edge in graph.edges:
        if edge.status == "active":
            key = f"active {edge.scene_kind}" if edge.scene_kind else "active"
        else:
            key = edge.reason or "filtered"
        groups.setdefault(key, []).append(edge)
    active = sorted(k for k in groups if k.startswith("active"))
    filtered = sorted((k for k in groups if not k.startswith("active")), key=lambda k: -len(groups[k]))
    colours = {"active": "#9aa7b8", "active REGULAR": "#9aa7b8", "active PURE_ROTATION": svg.PALETTE[4]}
    width = 1.2 if len(graph.edges) < 400 else 0.5
    ring = len(view_ids) > MAX_MARKS  # a dot per view would be a solid ring: the ring, under the edges
    if ring:
        turn = np.linspace(0.0, 2 * np.pi, 361)
        chart.line(np.cos(turn), np.sin(turn), color=svg.PALETTE[0], width=1.0, label=f"{len(view_ids)} views")
    for k, key in enumerate(active + filtered):
        edges = groups[key]
        colour = colours.get(key, svg.PALETTE[[3, 1, 5, 6, 8, 9, 0, 2][k % 8]] if key in filtered else svg.PALETTE[7])
        step = -(-len(edges) // MAX_MARKS)
        x0, y0 = zip(*(position[e.i] for e in edges[::step]))
        x1, y1 = zip(*(position[e.j] for e in edges[::step]))
        sampled = f", 1 in {step} drawn" if step > 1 else ""
        chart.segments(x0, y0, x1, y1, color=colour, width=width if key in active else 1.6,
                       dashed=key in filtered, label=f"{key} ({len(edges)}{sampled})",
                       opacity=0.6 if key in active else 0.9)
    unregistered = set(graph.unregistered_views)
    names = [graph.views[v].name for v in view_ids]
    xy = np.array([position[v] for v in view_ids])
    colour_of = np.array([v in unregistered for v in view_ids])
    if ring:  # the views outside the largest component still marked
        colour_of_views = ((colour_of, svg.PALETTE[3], "view outside the largest component"),)
    else:
        colour_of_views = ((~colour_of, svg.PALETTE[0], "view"),
                           (colour_of, svg.PALETTE[3], "view outside the largest component"))
    for mask, colour, label in colour_of_views:
        if mask.any():
            chart.points(xy[mask, 0], xy[mask, 1], color=colour, radius=4 if len(view_ids) < 200 else 2,
                         label=label, titles=[n for n, m in zip(names, mask) if m])
    if len(view_ids) <= 60:
        for (x, y), name in zip(xy, names):
            chart.text(1.08 * x - (0.12 if x < -0.2 else 0.0), 1.08 * y, name, size=9)
    return figure(svg.data_uri(chart.svg()), "View graph (views on a circle in id order)", "fig-view-graph")


def top_view_axes(R_cam_from_world: np.ndarray) -> np.ndarray:
    """(2, 3) world directions of a top view: right and forward of the cameras, on the plane
    normal to their mean up direction (image y points down, so up is -y)."""
    R = np.asarray(R_cam_from_world, dtype=float)
    up = -R[:, 1, :].mean(axis=0)
    forward = R[:, 2, :].mean(axis=0)
    up /= np.linalg.norm(up) or 1.0
    forward = forward - (forward @ up) * up
    if np.linalg.norm(forward) < 1e-9:
        forward = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    forward /= np.linalg.norm(forward)
    return np.stack([np.cross(forward, up), forward])


def top_view_figure(scene: SfMScene) -> str | None:
    posed = sorted(scene.poses)
    if len(posed) < 2:
        return None
    R = np.stack([scene.poses[v].R_cam_from_world for v in posed])
    centres = np.stack([scene.poses[v].center for v in posed])
    axes = top_view_axes(R)
    c2 = centres @ axes.T
    extent = float(np.ptp(c2, axis=0).max()) or 1.0
    points2 = np.zeros((0, 2))
    if scene.structure is not None and len(scene.structure.points):
        points = np.asarray(scene.structure.points, dtype=float)
        step = max(1, len(points) // TOP_VIEW_POINTS)
        points2 = points[::step] @ axes.T
        # the points' bulk, so that a few far points do not shrink the cameras to a dot
        low, high = np.quantile(points2, 0.02, axis=0), np.quantile(points2, 0.98, axis=0)
        points2 = points2[np.all((points2 >= low) & (points2 <= high), axis=1)]
    both = np.concatenate([c2, points2]) if len(points2) else c2
    pad = 0.08 * (float(np.ptp(both, axis=0).max()) or 1.0)
    chart = svg.Chart(720, 620, (both[:, 0].min() - pad, both[:, 0].max() + pad),
                      (both[:, 1].min() - pad, both[:, 1].max() + pad), title="Cameras and points, top view",
                      xlabel="right (world units)", ylabel="forward (world units)", equal=True)
    if len(points2):
        chart.points(points2[:, 0], points2[:, 1], color="#b0b0b0", radius=1.0, opacity=0.6,
                     label=f"points (1 in {step})" if step > 1 else "points")
    every = -(-len(posed) // MAX_MARKS)  # one camera in ``every`` drawn
    shown = slice(None, None, every)
    direction = (R[shown, 2, :] @ axes.T)
    norm = np.linalg.norm(direction, axis=1, keepdims=True)
    length = 0.08 * extent
    if len(posed) > 40:  # a long capture: arrows of a few camera spacings, not a band of 8 % of its length
        spacing = float(np.median(np.linalg.norm(np.diff(c2[shown], axis=0), axis=1))) if c2[shown].shape[0] > 1 else 0
        length = min(length, 3.0 * spacing) or length
    tips = c2[shown] + length * direction / np.where(norm > 0, norm, 1.0)
    chart.segments(c2[shown, 0], c2[shown, 1], tips[:, 0], tips[:, 1], color=svg.PALETTE[3], width=1.5,
                   label="viewing direction")
    names = [scene.views[v].name for v in posed]
    chart.points(c2[shown, 0], c2[shown, 1], color=svg.PALETTE[0], radius=3.5 if every == 1 else 1.5,
                 label="camera centres" + (f" (1 in {every} of {len(posed)})" if every > 1 else ""),
                 titles=names[shown])
    if len(posed) <= 40:
        for (x, y), name in zip(c2, names):
            chart.text(x, y, name, size=9)
    return figure(svg.data_uri(chart.svg()), "Camera centres and viewing directions, top view (estimated)",
                   "fig-top-view")
