"""What `rotonly run` and the stage commands show while they work: a progress bar over the
stages when stderr is a terminal (the RANSAC and GRRM stages add their own bars), and with
``-v`` per-stage detail lines (time, edge counts per filter reason, the stage report's numbers).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager

logger = logging.getLogger(__name__)

#: set to 1: reports/resources.json holds each stage's own peak (scripts/bench/scale.py)
STAGE_PEAKS_VARIABLE = "ROTONLY_STAGE_PEAKS"

#: longest detail line; longer ones are continued on the next line
DETAIL_WIDTH = 100


class StageMonitor:
    """``with StageMonitor(stages, progress) as monitor: with monitor.stage(name): ...``.
    Set ``monitor.run`` once the run exists: the detail lines read its view graph."""

    def __init__(self, stages: Sequence[str], progress: bool):
        self.stages = list(stages)
        self.progress = progress
        self.run = None
        self._bar = None
        self._stack = ExitStack()
        #: per stage: wall time (s, summed over the calibration's passes), the resident memory
        #: at its end (MB, after the freed heap went back) and the high-water mark (MB): the
        #: process's so far, or with ROTONLY_STAGE_PEAKS=1 in the environment the stage's own
        #: (the mark is reset at each stage's start, which also lowers the whole run's peak
        #: that getrusage and `time -v` report to the last stage's: for benchmarks only):
        #: reports/resources.json
        self.resources: dict[str, dict] = {}
        self.stage_peaks = os.environ.get(STAGE_PEAKS_VARIABLE) == "1"

    def __enter__(self) -> StageMonitor:
        if self.progress:
            from tqdm.contrib.logging import logging_redirect_tqdm

            from rotonly_cli.runtime.progress import progress_bar

            self._stack.enter_context(logging_redirect_tqdm())  # log lines print above the bars
            self._bar = self._stack.enter_context(progress_bar(
                total=len(self.stages), unit="stage", leave=False,
                bar_format="{desc:<12} {n_fmt}/{total_fmt} stages |{bar:24}| {elapsed}"))
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if self._bar is not None:
            self._bar.set_description_str(name, refresh=True)
        own_peak = self.stage_peaks and reset_peak_rss()
        start = time.perf_counter()
        yield
        seconds = time.perf_counter() - start
        entry = self.resources.setdefault(name, {"time_s": 0.0, "peak_rss_mb": None, "rss_end_mb": None,
                                                 "peak_is_stage_own": own_peak})
        entry["time_s"] += seconds
        peak = peak_rss_mb()
        if peak is not None:
            entry["peak_rss_mb"] = max(entry["peak_rss_mb"] or 0.0, peak)
        from rotonly_cli.runtime.startup import release_freed_heap

        release_freed_heap()  # the stage's transients leave the resident memory before the next stage
        entry["rss_end_mb"] = status_mb("VmRSS")
        if self._bar is not None:
            self._bar.update(1)
        if self.run is not None and logger.isEnabledFor(logging.DEBUG):
            for line in stage_detail(name, self.run, time.perf_counter() - start):
                logger.debug(line)


def reset_peak_rss() -> bool:
    """Reset the kernel's resident high-water mark of this process (Linux: VmHWM); False where
    that is not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float | None:
    """The process's resident high-water mark (MB) since the last :func:`reset_peak_rss`."""
    return status_mb("VmHWM")


def status_mb(key: str) -> float | None:
    """A memory figure of /proc/self/status (VmRSS, VmHWM, ...) in MB; None where unknown."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _short(value) -> str | None:
    """A report value as a short text; None for lists and dicts (too long for a line)."""
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    return None


def _wrapped(head: str, items: list[str]) -> list[str]:
    lines, line = [], head
    for item in items:
        if len(line) + len(item) + 2 > DETAIL_WIDTH and line != head:
            lines.append(line.rstrip(","))
            line = " " * len(head)
        line += f" {item},"
    lines.append(line.rstrip(","))
    return lines


def stage_detail(name: str, run, seconds: float) -> list[str]:
    """The -v lines after stage ``name``: its time, the view graph's edge counts per filter
    reason, and the stage report's scalar numbers (the full report is reports/<name>.json)."""
    counts = run.graph.counts()
    reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(counts.get("filtered_by_reason", {}).items()))
    lines = [f"{name}: {seconds:.3f} s; {counts['active_edges']} of {counts['edges']} edges active"
             + (f" (filtered: {reasons})" if reasons else "")
             + f"; {len(counts['unregistered_views'])} of {counts['views']} views outside the largest component"]
    report = run.reports.get(name, {})
    items = [f"{key}={text}" for key, value in sorted(report.items())
             if key != "time_s" and (text := _short(value)) is not None]
    if items:
        lines += _wrapped(f"{name} report:", items)
    return lines
