"""Progress lines a user sees in a pipe or a CI log (issue 49 point 7).

When stderr is not a terminal (where the tqdm bars of runtime/progress.py show), a run writes
every :data:`INTERVAL_S` seconds one line about the innermost piece of work in progress::

    04:51:07 load/RANSAC: 812/2000 (41%) ETA 01:02
    04:52:40 optimize/GRRM: 7/100 (7%) ETA 19:53     (GRRM's iterations: the most it may take)
    04:53:12 translate: running for 00:41           (a stage with no counted loop)

The long loops count their steps into a :func:`task` (the RANSAC runs of the load stage,
GRRM's iterations, the rejection rounds); a stage is a task without a total. The lines come
from an interval timer (SIGALRM), not a thread: a live thread would keep runtime/parallel
from forking. The handler runs in the main thread between bytecodes, so a single C call
(one sparse factorisation) delays it; it writes with ``os.write``, never through a buffered
stream the main thread may be in the middle of.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

#: seconds between two progress lines (tests lower it)
INTERVAL_S = 30.0


@dataclass
class _Task:
    name: str
    total: int | None
    done: int = 0
    started: float = field(default_factory=time.monotonic)


_TASKS: list[_Task] = []  # innermost last
_STATE = {"fd": None}  # the file descriptor lines go to while a heartbeat runs


def running() -> bool:
    """Whether progress lines are being written (a :func:`heartbeat` is on)."""
    return _STATE["fd"] is not None


def _clock(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 60:02d}:{seconds % 60:02d}"


def progress_line(now: float | None = None) -> str | None:
    """The line for the innermost task (None without one): ``HH:MM:SS <stage>[/<loop>]:
    done/total (pct) ETA mm:ss``, or ``... running for mm:ss`` without a total."""
    if not _TASKS:
        return None
    now = time.monotonic() if now is None else now
    task = next((t for t in reversed(_TASKS) if t.total), _TASKS[-1])
    name = task.name if task is _TASKS[0] else f"{_TASKS[0].name}/{task.name}"
    stamp = time.strftime("%H:%M:%S")
    elapsed = now - task.started
    if not task.total:
        return f"{stamp} {name}: running for {_clock(elapsed)}"
    done = min(task.done, task.total)
    eta = _clock(elapsed * (task.total - done) / done) if done else "--:--"
    return f"{stamp} {name}: {done}/{task.total} ({100 * done // task.total}%) ETA {eta}"


def _beat(signum, frame) -> None:
    line = progress_line()
    fd = _STATE["fd"]
    if line is not None and fd is not None:
        try:
            os.write(fd, (line + "\n").encode("utf-8", "replace"))
        except OSError:  # a closed pipe: no more lines
            _STATE["fd"] = None


@contextmanager
def task(name: str, total: int | None = None) -> Iterator[Callable[[int], None]]:
    """A piece of work of ``total`` steps (None: not counted); yields ``advance(steps=1)``."""
    entry = _Task(name, total)
    _TASKS.append(entry)

    def advance(steps: int = 1) -> None:
        entry.done += steps

    try:
        yield advance
    finally:
        _TASKS.remove(entry)


def advance(steps: int = 1) -> None:
    """One step more for the innermost task (no-op without one)."""
    if _TASKS:
        _TASKS[-1].done += steps


def _quiet() -> bool:
    """-q (or no logging set up, as for a Python caller): the stderr handlers show no INFO."""
    root = logging.getLogger()
    shown = [h for h in root.handlers if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)
             and getattr(h, "stream", None) in (sys.stderr, sys.__stderr__)]
    return not shown or all(max(h.level, root.level) > logging.INFO for h in shown)


def _stderr_fd() -> int | None:
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        return None
    return None if os.isatty(fd) else fd


@contextmanager
def heartbeat(enabled: bool = True) -> Iterator[None]:
    """Progress lines every :data:`INTERVAL_S` s within, when ``enabled``, stderr is a pipe or
    a file, logging shows INFO on it (not -q) and this is the main thread of a POSIX
    process; else nothing. Nested: the outer one writes."""
    fd = _stderr_fd() if enabled and not running() else None
    if fd is None or _quiet() or threading.current_thread() is not threading.main_thread() \
            or not hasattr(signal, "setitimer"):
        yield
        return
    previous = signal.signal(signal.SIGALRM, _beat)
    signal.siginterrupt(signal.SIGALRM, False)  # system calls restart rather than fail with EINTR
    _STATE["fd"] = fd
    signal.setitimer(signal.ITIMER_REAL, INTERVAL_S, INTERVAL_S)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0, 0)
        _STATE["fd"] = None
        signal.signal(signal.SIGALRM, previous)
