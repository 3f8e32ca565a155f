"""Progress bars (tqdm) without tqdm's monitor thread.

tqdm starts a daemon "tqdm_monitor" thread with the first bar and keeps it for the life of
the process; it only tunes the refresh interval of bars that stall. A live thread makes a
later fork unsafe (a fork copies only the calling thread), so rotonly_cli.runtime.parallel would
refine in one process for the rest of a `rotonly run` that showed a bar. Bars come from here.
"""

from __future__ import annotations


def progress_bar(iterable=None, **kwargs):
    """``tqdm.tqdm(iterable, **kwargs)`` with the monitor thread off."""
    import tqdm  # imported only for a bar (10-20 ms of a run otherwise)

    tqdm.tqdm.monitor_interval = 0
    return tqdm.tqdm(iterable, **kwargs)
