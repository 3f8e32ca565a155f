"""Start-up and garbage-collector costs of the ``rotonly`` process (docs/tuning.md has the numbers).

scipy builds its array-API namespace by cloning every public attribute of numpy
(``scipy._lib.array_api_compat.numpy``, imported by ``scipy.sparse`` and ``scipy.linalg``).
numpy 2 loads its optional submodules on first attribute access, so that clone imports
``numpy.f2py`` (with its Fortran parser), ``numpy.testing``, ``numpy.ma``,
``numpy.polynomial`` and a few more that no command needs: a third of scipy's import time.

:func:`defer_unused_numpy_submodules` puts each of them into ``sys.modules`` (and on the
``numpy`` package) as a module object created by the standard library's
``importlib.util.LazyLoader``: the clone binds the object without touching it, and the
module's code runs in full on its first attribute access, so code that does use
``numpy.ma`` or ``numpy.testing`` later (matplotlib in ``rotonly eval``) gets the real module.
Only the console script calls it, before any command runs; importing rotonly as a
library changes nothing.

Two process-wide settings are made by the console script too, before numpy is imported:

* :func:`one_blas_thread_per_process`: rotonly parallelises by processes (``--jobs``), and the
  BLAS calls it makes are small (a few hundred flops each). A multi-threaded OpenBLAS wakes its
  thread pool for them, and the pool then busy-waits for the next call, on the core the other
  rotonly process needs (docs/tuning.md "Process start-up and shutdown").
* :func:`keep_freed_heap`: numpy's arrays of 0.1–30 MB are allocated and freed thousands of
  times per run. glibc's defaults hand that memory back to the kernel (munmap, heap trimming)
  and every reuse faults it in again, zero-filled; kept in the heap, half the page faults and
  the system time go.
"""

from __future__ import annotations

import ctypes
import gc
import importlib.util
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

#: numpy submodules that scipy's namespace clone imports and that rotonly's commands do not
#: need at start-up. numpy.typing is left out: scipy imports it explicitly before cloning.
DEFERRED_NUMPY_SUBMODULES = ("f2py", "testing", "ma", "polynomial", "ctypeslib", "char", "rec", "strings")


def defer_unused_numpy_submodules(names: tuple[str, ...] = DEFERRED_NUMPY_SUBMODULES) -> list[str]:
    """Register the named ``numpy`` submodules as lazily loaded; returns the names deferred
    (a submodule that is already imported, or that this numpy does not have, is skipped)."""
    import numpy

    deferred = []
    for name in names:
        full_name = f"numpy.{name}"
        if full_name in sys.modules:
            continue
        spec = importlib.util.find_spec(full_name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[full_name] = module
        spec.loader.exec_module(module)  # only arms the lazy load; nothing of numpy.<name> runs yet
        # also bind it on the package: numpy's module __getattr__ would import it again, and
        # ``import numpy.<name>`` finds a module in sys.modules without setting the attribute
        setattr(numpy, name, module)
        deferred.append(name)
    return deferred


#: the variables the BLAS libraries numpy and scipy are built with read for their thread count
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread_per_process(environ: dict[str, str] | None = None) -> list[str]:
    """Set each of :data:`BLAS_THREAD_VARIABLES` to 1 where the user has not set it; returns the
    names set. Read by the BLAS library when it is loaded, so this must run before numpy is
    imported; the forked workers inherit it, and so does any process rotonly starts."""
    environ = os.environ if environ is None else environ
    chosen = [name for name in BLAS_THREAD_VARIABLES if name not in environ]
    for name in chosen:
        environ[name] = "1"
    return chosen


#: mallopt(3) parameters (glibc's malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: mallopt(3) documents 32 MiB as the mmap threshold's upper limit on 64-bit systems
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: free memory at the top of the heap kept for reuse; a run on a few dozen views peaks far below
TRIM_THRESHOLD_BYTES = 512 * 1024 * 1024


def keep_freed_heap(mmap_threshold: int = MMAP_THRESHOLD_BYTES, trim_threshold: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Serve allocations below ``mmap_threshold`` from the heap and keep up to ``trim_threshold``
    bytes of freed heap instead of handing them back to the kernel (glibc's mallopt). Returns
    whether the C library took both settings: False where it has no mallopt (macOS) or refuses
    a value (musl's mallopt does nothing). Setting either also ends glibc's own adjustment of
    the mmap threshold, which only follows the sizes of blocks already freed."""
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    taken = mallopt(M_MMAP_THRESHOLD, mmap_threshold) == 1
    return mallopt(M_TRIM_THRESHOLD, trim_threshold) == 1 and taken


def release_freed_heap() -> bool:
    """Hand the heap's free pages back to the kernel (glibc's malloc_trim(0), which also
    releases free pages in the middle of the heap, below the top that M_TRIM_THRESHOLD keeps).
    Called between stages: a stage's transients of a large collection would otherwise stay in
    the process's resident memory for the rest of the run, under the next stage's peak (issue
    49: 6.8 GB resident after identification at 1000 views, of which most was free heap).
    False where the C library has no malloc_trim."""
    trim = getattr(ctypes.CDLL(None), "malloc_trim", None)
    if trim is None:
        return False
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    trim(0)
    return True


@contextmanager
def collector_paused() -> Iterator[None]:
    """CPython's cyclic garbage collector off for the block (restored after).

    A run allocates ~10⁵ small containers per 10⁴ points; every 700 of them trigger a
    collection, whose older generations re-scan every live object, the imported modules
    included. The stages build no reference cycles per point or per iteration, so reference
    counting alone frees what they drop; the few cycles left (thread pools, loggers) are
    collected once the collector is back on."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def rotonly_process_settings() -> None:
    """The process settings of ``rotonly`` (:func:`one_blas_thread_per_process`,
    :func:`keep_freed_heap`), for the console script and for benchmarks that time rotonly's
    stages in their own process; before numpy is imported."""
    one_blas_thread_per_process()
    keep_freed_heap()
