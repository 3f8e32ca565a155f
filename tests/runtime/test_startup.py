"""The console script's start-up: numpy submodules deferred until first use."""

from __future__ import annotations

import subprocess
import sys
import textwrap

PROBE = textwrap.dedent("""
    import sys
    from rotonly_cli.runtime.startup import defer_unused_numpy_submodules, DEFERRED_NUMPY_SUBMODULES
    deferred = defer_unused_numpy_submodules()
    import numpy as np
    import scipy.linalg, scipy.sparse.csgraph, scipy.sparse.linalg, scipy.spatial.transform
    # scipy's namespace clone has bound them, but none has run: f2py's Fortran parser,
    # numpy.testing's utilities and numpy.ma's core are not imported
    loaded_after_scipy = [m for m in ("numpy.f2py.crackfortran", "numpy.testing._private.utils", "numpy.ma.core")
                          if m in sys.modules]
    # first use runs the real module
    np.testing.assert_allclose([1.0], [1.0 + 1e-12])
    masked_sum = int(np.ma.masked_array([1, 2, 3], mask=[0, 1, 0]).sum())
    from numpy.testing import assert_array_equal
    assert_array_equal([1], [1])
    loaded_after_use = "numpy.ma.core" in sys.modules and "numpy.testing._private.utils" in sys.modules
    print(sorted(deferred) == sorted(DEFERRED_NUMPY_SUBMODULES), loaded_after_scipy, masked_sum, loaded_after_use)
    """)


def test_deferred_numpy_submodules_are_skipped_by_scipy_import_and_real_on_first_use():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True).stdout
    assert out.split("\n")[0] == "True [] 4 True"


def test_defer_skips_submodules_already_imported_and_unknown_names():
    import numpy
    import numpy.testing  # imported for real here

    from rotonly_cli.runtime.startup import defer_unused_numpy_submodules

    assert defer_unused_numpy_submodules(("testing", "no_such_submodule")) == []
    assert type(sys.modules["numpy.testing"]) is type(numpy) and numpy.testing.assert_allclose


def test_console_main_defers_before_running_the_command(monkeypatch):
    from rotonly_cli import cli
    from rotonly_cli.runtime import startup

    calls = []
    monkeypatch.setattr(startup, "defer_unused_numpy_submodules", lambda: calls.append("defer"))
    monkeypatch.setattr(cli, "main", lambda: calls.append("main"))
    monkeypatch.setattr("gc.freeze", lambda: None)
    cli.console_main()
    assert calls == ["defer", "main"]
