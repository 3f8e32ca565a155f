"""Imported by every worker process of a ``--cluster local:N`` run as it starts (a Dask
preload, runtime/cluster.py), restarted ones too: the worker ignores SIGINT. Ctrl-C in a
terminal reaches the whole process group; the rotonly process answers it (exit 130) and closes
the local cluster, whose workers would otherwise each print a traceback."""

from __future__ import annotations

import signal

try:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
except ValueError:  # not the main thread of the worker process: Ctrl-C stays as it was
    pass
