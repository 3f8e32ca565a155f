"""Imported by every worker process of a ``--cluster local:N`` run as it starts (a Dask
preload, runtime/cluster.py), restarted ones too: the worker ignores SIGINT. Ctrl-C in a
terminal reaches the whole process group; the rotonly process answers it (exit 130) and closes
the local cluster, whose workers would otherwise each print a traceback.

It also gives the worker rotonly's heap settings (runtime/startup.keep_freed_heap): Dask's nanny
starts workers with MALLOC_TRIM_THRESHOLD_=65536, under which every large temporary of a stage's
per-edge work is handed back to the kernel and page-faulted afresh on the next allocation (the
200-view simulation's identification and TRRM tasks ran 3x slower than in --jobs' forked processes,
with 3.5x the system time at 1000 views). BLAS is one thread per worker already (the nanny's
OPENBLAS_NUM_THREADS=1). Workers started by hand get both with ``--preload rotonly_cli.runtime.cluster_worker``."""

from __future__ import annotations

import signal

from rotonly_cli.runtime.startup import keep_freed_heap

keep_freed_heap()

try:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
except ValueError:  # not the main thread of the worker process: Ctrl-C stays as it was
    pass
