"""Ctrl-C in the command-line tool once a command's outcome is on disk (issue 53).

`rotonly run` puts its new workspace in place in one step (io/atomic.Staging.commit, which
defers Ctrl-C until it is done). From that moment the command has succeeded, so a Ctrl-C
no longer changes its exit code: the CLI's SIGINT handler (:func:`cli_handler`) raises
KeyboardInterrupt (exit 130, OUT as it was) only until :func:`outcome_written` is called, and
ignores Ctrl-C after it (exit 0, OUT new; the summary is still printed). Library callers keep
their own handler: for them a Ctrl-C during the commit is delivered once it is done.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: whether this command put its outcome in place (reset by :func:`cli_handling`)
_WRITTEN = [False]


def outcome_written() -> None:
    """The command's output is in place: from now on Ctrl-C does not change its outcome."""
    _WRITTEN[0] = True


def written() -> bool:
    return _WRITTEN[0]


def cli_handler(signum, frame) -> None:
    """SIGINT in the CLI: KeyboardInterrupt, unless the outcome is already written (then
    nothing, not even a log line: the handler may run inside a logging call)."""
    if not _WRITTEN[0]:
        raise KeyboardInterrupt


def install() -> None:
    """:func:`cli_handler` for the rest of the process (the console script, which ends right
    after the command: a handler restored before the interpreter's exit could turn a late
    Ctrl-C into a traceback)."""
    signal.signal(signal.SIGINT, cli_handler)


@contextmanager
def cli_handling() -> Iterator[None]:
    """One command: nothing written yet, and :func:`cli_handler` in force (in the main thread)
    unless it already is; a handler replaced here is restored at the end (in-process callers)."""
    _WRITTEN[0] = False
    replaced = None
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is not cli_handler:
        replaced = signal.signal(signal.SIGINT, cli_handler)
    try:
        yield
    finally:
        if replaced is not None:
            signal.signal(signal.SIGINT, replaced)
