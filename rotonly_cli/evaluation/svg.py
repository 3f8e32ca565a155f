"""Small SVG charts for OUT/report.html: bars, histograms, points and segments on axes with
tick marks. Hand-written so that the report costs milliseconds on every run (matplotlib's
import alone takes longer than a small run); the figures go into the page as data URIs."""

from __future__ import annotations

import base64
import math
from collections.abc import Sequence
from html import escape

import numpy as np

#: matplotlib's tab10, the colours of the eval figures
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf")
FONT = "font-family:sans-serif"


def nice_ticks(low: float, high: float, count: int = 6) -> list[float]:
    """About ``count`` round tick values (1, 2, 5 x 10^k steps) covering [low, high]."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return []
    if high <= low:
        high = low + (abs(low) if low else 1.0)
    raw = (high - low) / max(count - 1, 1)
    magnitude = 10.0 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw)
    first = math.ceil(low / step - 1e-9) * step
    return [round(first + k * step, 12) for k in range(int((high - first) / step + 1e-9) + 1)]


def _label(value: float) -> str:
    return f"{value:.6g}" if abs(value) >= 1e-3 or value == 0 else f"{value:.2e}"


def _inside(limits: tuple[float, float]) -> list[float]:
    """The :func:`nice_ticks` of an axis that lie on it."""
    low, high = limits
    return [value for value in nice_ticks(low, high) if low - 1e-12 <= value <= high + 1e-12]


class Chart:
    """One plot: data coordinates in ``xlim`` x ``ylim`` drawn into a ``width`` x ``height``
    pixel SVG. ``categories``: names of x = 0, 1, ... for bar charts (labelled, rotated)."""

    def __init__(self, width: int, height: int, xlim: tuple[float, float], ylim: tuple[float, float], *,
                 title: str = "", xlabel: str = "", ylabel: str = "", categories: Sequence[str] | None = None,
                 equal: bool = False, margins: tuple[int, int, int, int] | None = None, axes: bool = True):
        self.width, self.height = width, height
        label_room = 0 if categories is None else min(110, 12 + 6 * max((len(c) for c in categories), default=0))
        self.left, self.right, self.top, self.bottom = margins or (62, 16, 30 if title else 12,
                                                                  (40 if xlabel else 24) + label_room)
        self.title, self.xlabel, self.ylabel, self.categories, self.axes = title, xlabel, ylabel, categories, axes
        (x0, x1), (y0, y1) = xlim, ylim
        if x1 <= x0:
            x0, x1 = x0 - 0.5, x0 + 0.5
        if y1 <= y0:
            y0, y1 = y0 - 0.5, y0 + 0.5
        if equal:  # one data unit is as long on both axes: widen the shorter range
            sx = (x1 - x0) / self.plot_width
            sy = (y1 - y0) / self.plot_height
            if sx > sy:
                pad = (sx * self.plot_height - (y1 - y0)) / 2
                y0, y1 = y0 - pad, y1 + pad
            else:
                pad = (sy * self.plot_width - (x1 - x0)) / 2
                x0, x1 = x0 - pad, x1 + pad
        self.xlim, self.ylim = (x0, x1), (y0, y1)
        self.body: list[str] = []
        self.legend: list[tuple[str, str, str]] = []  # (label, colour, kind)

    @property
    def plot_width(self) -> float:
        return self.width - self.left - self.right

    @property
    def plot_height(self) -> float:
        return self.height - self.top - self.bottom

    def px(self, x) -> np.ndarray:
        x0, x1 = self.xlim
        return self.left + (np.asarray(x, dtype=float) - x0) / (x1 - x0) * self.plot_width

    def py(self, y) -> np.ndarray:
        y0, y1 = self.ylim
        return self.top + (1.0 - (np.asarray(y, dtype=float) - y0) / (y1 - y0)) * self.plot_height

    # ------------------------------------------------------------------ marks
    def bars(self, x, heights, width: float = 0.8, color: str = PALETTE[0], label: str | None = None,
             offset: float = 0.0) -> None:
        """Bars centred at ``x + offset``, ``width`` data units wide, from 0 up to ``heights``."""
        x = np.asarray(x, dtype=float) + offset
        heights = np.nan_to_num(np.asarray(heights, dtype=float))
        left, right = self.px(x - width / 2), self.px(x + width / 2)
        top, base = self.py(np.maximum(heights, 0)), self.py(0.0)
        self.body.append(f'<g fill="{color}">' + "".join(
            f'<rect x="{a:.1f}" y="{t:.1f}" width="{max(b - a, 0.5):.1f}" height="{max(base - t, 0):.1f}"/>'
            for a, b, t in zip(left, right, top)) + "</g>")
        if label:
            self.legend.append((label, color, "box"))

    def points(self, x, y, color: str = PALETTE[0], radius: float = 2.5, label: str | None = None,
               opacity: float = 1.0, titles: Sequence[str] | None = None) -> None:
        xs, ys = self.px(x), self.py(y)
        if titles is None:
            dots = "".join(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="{radius}"/>' for a, b in zip(xs, ys))
        else:
            dots = "".join(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="{radius}"><title>{escape(t)}</title></circle>'
                           for a, b, t in zip(xs, ys, titles))
        self.body.append(f'<g fill="{color}" fill-opacity="{opacity}">{dots}</g>')
        if label:
            self.legend.append((label, color, "dot"))

    def segments(self, x0, y0, x1, y1, color: str = PALETTE[0], width: float = 1.0, label: str | None = None,
                 dashed: bool = False, opacity: float = 1.0) -> None:
        a, b, c, d = self.px(x0), self.py(y0), self.px(x1), self.py(y1)
        path = "".join(f"M{p:.1f} {q:.1f}L{r:.1f} {s:.1f}" for p, q, r, s in zip(a, b, c, d))
        dash = ' stroke-dasharray="5 3"' if dashed else ""
        self.body.append(f'<path d="{path}" stroke="{color}" stroke-width="{width}" stroke-opacity="{opacity}" '
                         f'fill="none"{dash}/>')
        if label:
            self.legend.append((label, color, "dash" if dashed else "line"))

    def line(self, x, y, color: str = PALETTE[0], width: float = 1.5, label: str | None = None) -> None:
        xs, ys = self.px(x), self.py(y)
        path = "M" + "L".join(f"{a:.1f} {b:.1f}" for a, b in zip(xs, ys))
        self.body.append(f'<path d="{path}" stroke="{color}" stroke-width="{width}" fill="none"/>')
        if label:
            self.legend.append((label, color, "line"))

    def text(self, x: float, y: float, text: str, size: int = 10, anchor: str = "start", color: str = "#333") -> None:
        self.body.append(f'<text x="{float(self.px(x)) + 3:.1f}" y="{float(self.py(y)) - 3:.1f}" font-size="{size}" '
                         f'text-anchor="{anchor}" fill="{color}" style="{FONT}">{escape(text)}</text>')

    def note(self, text: str) -> None:
        """A centred message (e.g. "no data")."""
        self.body.append(f'<text x="{self.left + self.plot_width / 2:.1f}" y="{self.top + self.plot_height / 2:.1f}" '
                         f'font-size="13" text-anchor="middle" fill="#777" style="{FONT}">{escape(text)}</text>')

    # ------------------------------------------------------------------ frame
    def _frame(self) -> list[str]:
        out = []
        left, top, w, h = self.left, self.top, self.plot_width, self.plot_height
        if self.axes:
            out.append(f'<rect x="{left}" y="{top}" width="{w:.1f}" height="{h:.1f}" fill="none" stroke="#888"/>')
            for value in _inside(self.ylim):
                y = float(self.py(value))
                out.append(f'<path d="M{left} {y:.1f}h{w:.1f}" stroke="#e4e4e4"/><text x="{left - 4}" '
                           f'y="{y + 3.5:.1f}" font-size="10" text-anchor="end" style="{FONT}">{_label(value)}</text>')
            if self.categories is None:
                for value in _inside(self.xlim):
                    x = float(self.px(value))
                    out.append(f'<path d="M{x:.1f} {top + h:.1f}v4" stroke="#888"/><text x="{x:.1f}" '
                               f'y="{top + h + 15:.1f}" font-size="10" text-anchor="middle" style="{FONT}">'
                               f'{_label(value)}</text>')
            else:
                step = max(1, math.ceil(len(self.categories) / 60))
                for k in range(0, len(self.categories), step):
                    x, y = float(self.px(k)), top + h + 8
                    out.append(f'<text x="{x:.1f}" y="{y:.1f}" font-size="9" text-anchor="end" '
                               f'transform="rotate(-60 {x:.1f} {y:.1f})" style="{FONT}">'
                               f'{escape(self.categories[k])}</text>')
        if self.title:
            out.append(f'<text x="{self.width / 2:.1f}" y="18" font-size="13" text-anchor="middle" '
                       f'style="{FONT};font-weight:bold">{escape(self.title)}</text>')
        if self.xlabel:
            out.append(f'<text x="{left + w / 2:.1f}" y="{self.height - 6}" font-size="11" text-anchor="middle" '
                       f'style="{FONT}">{escape(self.xlabel)}</text>')
        if self.ylabel:
            out.append(f'<text x="14" y="{top + h / 2:.1f}" font-size="11" text-anchor="middle" '
                       f'transform="rotate(-90 14 {top + h / 2:.1f})" style="{FONT}">{escape(self.ylabel)}</text>')
        return out

    def _legend(self) -> list[str]:
        if not self.legend:
            return []
        rows = []
        width = 26 + 6.2 * max(len(label) for label, _, _ in self.legend)
        x, y = self.left + self.plot_width - width - 6, self.top + 6
        rows.append(f'<rect x="{x:.1f}" y="{y:.1f}" width="{width:.1f}" height="{14 * len(self.legend) + 6}" '
                    'fill="white" fill-opacity="0.85" stroke="#ccc"/>')
        for k, (label, color, kind) in enumerate(self.legend):
            cy = y + 11 + 14 * k
            if kind == "box":
                rows.append(f'<rect x="{x + 5:.1f}" y="{cy - 5:.1f}" width="12" height="9" fill="{color}"/>')
            elif kind == "dot":
                rows.append(f'<circle cx="{x + 11:.1f}" cy="{cy:.1f}" r="3.5" fill="{color}"/>')
            else:
                dash = ' stroke-dasharray="5 3"' if kind == "dash" else ""
                rows.append(f'<path d="M{x + 4:.1f} {cy:.1f}h14" stroke="{color}" stroke-width="2"{dash}/>')
            rows.append(f'<text x="{x + 22:.1f}" y="{cy + 3.5:.1f}" font-size="10" style="{FONT}">'
                        f'{escape(label)}</text>')
        return rows

    def svg(self) -> str:
        parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.width}" height="{self.height}" '
                 f'viewBox="0 0 {self.width} {self.height}">', '<rect width="100%" height="100%" fill="white"/>',
                 *self._frame(), f'<svg x="{self.left}" y="{self.top}" width="{self.plot_width:.1f}" '
                 f'height="{self.plot_height:.1f}" overflow="hidden"><g transform="translate({-self.left} '
                 f'{-self.top})">', *self.body, "</g></svg>", *self._legend(), "</svg>"]
        return "".join(parts)


def data_uri(svg: str) -> str:
    """``svg`` as a data URI for an <img> (base64: no escaping questions)."""
    return "data:image/svg+xml;base64," + base64.b64encode(svg.encode("utf-8")).decode("ascii")


def png_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")
