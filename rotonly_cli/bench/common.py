"""Shared helpers of the benchmarks: statistics, markdown tables, atomic result folders,
process pools and progress bars."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.io.atomic import staging_dir


def error_deg(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """Geodesic rotation error (deg), eq:rotationerrorcalculate."""
    return np.degrees(so3.geodesic_angle(R_est, R_true))


def stats(values: Sequence[float]) -> dict:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "max": float("nan"), "count": 0}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "max": float(v.max()), "count": int(v.size)}


def fmt(value: float, digits: int = 4) -> str:
    if value is None or not np.isfinite(value):
        return "–"
    if value != 0 and abs(value) < 10 ** -digits:
        return f"{value:.2e}"
    return f"{value:.{digits}f}"


def markdown_table(head: Sequence[str], rows: Iterable[Sequence[str]], bold_min_columns: Sequence[int] = ()) -> str:
    rows = [list(r) for r in rows]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join(r) + " |")
    return "\n".join(lines)


@contextmanager
def result_dir(target: str | os.PathLike) -> Iterator[Path]:
    """A temporary sibling of ``target`` that replaces it on success (no partial outputs)."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    with staging_dir(target) as tmp:
        yield tmp


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def write_json(path: Path, payload: dict) -> None:
    path.write_text(json.dumps(payload, indent=1, default=_json_default, allow_nan=True) + "\n")


class CellCheckpoint:
    """Finished cells of a long benchmark, one JSON line each, in a hidden file beside the
    output folder (``.<name>.cells.jsonl``). A run stopped part-way keeps them, and the next
    run with the same settings reuses them instead of recomputing; a finished run deletes the
    file. Cells computed under other settings are ignored, never mixed in."""

    def __init__(self, out_dir: str | os.PathLike, settings: dict):
        out_dir = Path(out_dir)
        self.path = out_dir.parent / f".{out_dir.name}.cells.jsonl"
        self.settings = json.loads(json.dumps(settings))
        self.done: dict[str, dict] = {}
        if self.path.exists():
            for line in self.path.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:  # a line cut short when the run was killed
                    continue
                if record.get("settings") == self.settings:
                    self.done[record["cell"]] = record["row"]
            if self.done:
                print(f"resuming: {len(self.done)} finished cell(s) from {self.path}", file=sys.stderr)

    def get_or_run(self, cell: tuple, compute: Callable[[], dict]) -> dict:
        key = json.dumps(list(cell))
        if key in self.done:
            return self.done[key]
        row = compute()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps(dict(settings=self.settings, cell=key, row=row), default=_json_default) + "\n")
        self.done[key] = row
        return row

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def parallel_map(fn: Callable, tasks: list, jobs: int, desc: str, progress: bool = True) -> list:
    """``[fn(t) for t in tasks]`` in order, over ``jobs`` forked processes, with a tqdm bar."""
    from rotonly_cli.runtime.progress import progress_bar

    bar = progress_bar(total=len(tasks), desc=desc, disable=not progress, file=sys.stderr, leave=False)
    try:
        if jobs > 1 and len(tasks) > 1:
            with mp.get_context("fork").Pool(min(jobs, len(tasks))) as pool:
                out = []
                for result in pool.imap(fn, tasks, chunksize=1):
                    out.append(result)
                    bar.update()
                # let the workers exit: the context's terminate() sends SIGTERM, on which
                # pycolmap's glog handler prints a stack trace per worker
                pool.close()
                pool.join()
                return out
        out = []
        for t in tasks:
            out.append(fn(t))
            bar.update()
        return out
    finally:
        bar.close()


def plot_curves(path: Path, panels: dict[str, dict[str, tuple[list, list]]], xlabel: str, ylabel: str,
                title: str, logy: bool = True) -> None:
    """One subplot per panel: {panel: {method: (x, y)}}; saved as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = len(panels)
    cols = min(k, 3)
    rows = (k + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, (panel, curves) in zip(axes.ravel(), panels.items()):
        for method, (x, y) in curves.items():
            y = np.asarray(y, dtype=float)
            if np.all(~np.isfinite(y)):
                continue
            ax.plot(x, y, marker="o", label=method)
        ax.set_title(panel)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        if logy:
            ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.ravel()[k:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def code_version() -> str:
    """``git describe`` of the rotonly checkout that is running (``-dirty``: uncommitted edits)."""
    import subprocess

    try:
        return subprocess.run(["git", "describe", "--always", "--dirty"], cwd=Path(__file__).resolve().parent,
                              capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
