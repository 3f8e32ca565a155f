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
"""

from __future__ import annotations

import gc
import importlib.util
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
