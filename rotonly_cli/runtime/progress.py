"""Progress bars (tqdm) without tqdm's monitor thread.

tqdm starts a daemon "tqdm_monitor" thread with the first bar and keeps it for the life of
the process; it only tunes the refresh interval of bars that stall. A live thread makes a
later fork unsafe (a fork copies only the calling thread), so rotonly_cli.runtime.parallel would
refine in one process for the rest of a `rotonly run` that showed a bar. Bars come from here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager


def progress_bar(iterable=None, **kwargs):
    """``tqdm.tqdm(iterable, **kwargs)`` with the monitor thread off."""
    import tqdm  # imported only for a bar (10-20 ms of a run otherwise)

    tqdm.tqdm.monitor_interval = 0
    return tqdm.tqdm(iterable, **kwargs)


@contextmanager
def iteration_bar(show: bool, total: int, desc: str) -> Iterator[Callable[[object], None] | None]:
    """A bar advanced by the callback it yields (None when ``show`` is false), for iterative
    solvers that report each iteration (GRRM's ``on_iteration``); it fills up at the end, as
    the solver may stop before ``total`` iterations."""
    if not show:  # in a pipe: the iterations counted for the progress lines (runtime/heartbeat)
        from rotonly_cli.runtime import heartbeat

        with heartbeat.task(desc, total) as advance:
            yield (lambda _record: advance()) if heartbeat.running() else None
        return
    with progress_bar(total=total, desc=desc, unit="it", leave=False) as bar:
        yield lambda _record: bar.update(1)
        bar.update(bar.total - bar.n)
