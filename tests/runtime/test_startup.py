"""The console script's start-up: one BLAS thread, freed heap kept, numpy submodules deferred until first use."""

from __future__ import annotations

import platform
import subprocess
import sys
import textwrap

import pytest

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


def test_console_main_sets_up_the_process_before_running_the_command(monkeypatch):
    from rotonly_cli import cli
    from rotonly_cli.runtime import startup

    calls = []
    monkeypatch.setattr(startup, "one_blas_thread_per_process", lambda: calls.append("blas"))
    monkeypatch.setattr(startup, "keep_freed_heap", lambda: calls.append("heap"))
    monkeypatch.setattr(startup, "defer_unused_numpy_submodules", lambda: calls.append("defer"))
    monkeypatch.setattr(cli, "main", lambda: calls.append("main"))
    monkeypatch.setattr("gc.freeze", lambda: None)
    cli.console_main()
    assert calls == ["blas", "heap", "defer", "main"]


CTRL_C_WHILE_THE_CLI_IS_IMPORTED = textwrap.dedent("""
    import os, signal, sys
    from rotonly_cli import console
    from rotonly_cli.runtime import interrupts
    assert signal.getsignal(signal.SIGINT) is interrupts.cli_handler, "no handler after the first import"
    assert "rotonly_cli.cli" not in sys.modules and "numpy" not in sys.modules and "click" not in sys.modules

    class CtrlCOnClick:  # the user's Ctrl-C arrives while click is being imported
        def find_spec(self, name, path=None, target=None):
            if name == "click":
                os.kill(os.getpid(), signal.SIGINT)
            return None

    sys.meta_path.insert(0, CtrlCOnClick())
    sys.argv = ["rotonly", "--version"]
    console.main()
    """)


def test_console_script_answers_ctrl_c_while_the_cli_is_imported_with_one_line_and_130():
    """rotonly_cli.console installs the CLI's Ctrl-C handler as its first statement, before the
    CLI, click or numpy are imported (issue 53: Ctrl-C in that start-up gave Python's traceback)."""
    completed = subprocess.run([sys.executable, "-c", CTRL_C_WHILE_THE_CLI_IS_IMPORTED],
                               capture_output=True, text=True, timeout=60)
    assert completed.returncode == 130, completed.stderr
    assert completed.stderr == "error: interrupted\n"
    assert completed.stdout == ""


def test_console_script_runs_the_cli():
    completed = subprocess.run([sys.executable, "-c", "import sys; sys.argv = ['rotonly', '--version'];"
                                "from rotonly_cli import console; console.main()"],
                               capture_output=True, text=True, timeout=60)
    assert (completed.returncode, completed.stdout.split()[:2]) == (0, ["rotonly,", "version"]), completed.stderr


def test_one_blas_thread_leaves_a_users_setting_alone():
    from rotonly_cli.runtime.startup import one_blas_thread_per_process

    environ = {"MKL_NUM_THREADS": "4", "PATH": "/bin"}
    assert one_blas_thread_per_process(environ) == ["OPENBLAS_NUM_THREADS"]
    assert environ == {"MKL_NUM_THREADS": "4", "PATH": "/bin", "OPENBLAS_NUM_THREADS": "1"}
    assert one_blas_thread_per_process(environ) == []


def test_console_script_children_see_one_blas_thread():
    probe = ("import os, sys; from rotonly_cli.runtime.startup import one_blas_thread_per_process; "
             "one_blas_thread_per_process(); import numpy; "
             "print(os.environ['OPENBLAS_NUM_THREADS'], 'numpy' in sys.modules)")
    environ = {k: v for k, v in __import__("os").environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, env=environ)
    assert out.stdout.split() == ["1", "True"]


HEAP_PROBE = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from rotonly_cli.runtime.startup import keep_freed_heap
    taken = keep_freed_heap() if sys.argv[1] == "keep" else None
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):  # the pattern of a stage's temporaries: allocated, written, freed
        a = np.ones(2**20); b = a * 2.0; del a, b
    print(taken, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_keep_freed_heap_stops_refaulting_freed_arrays():
    def run(mode):
        out = subprocess.run([sys.executable, "-c", HEAP_PROBE, mode], capture_output=True, text=True, check=True)
        taken, faults = out.stdout.split()
        return taken, int(faults)

    default_taken, default_faults = run("default")
    taken, faults = run("keep")
    # 40 arrays of 8 MB: glibc's defaults map and unmap each (~1000 faults per loop here, some
    # on huge pages), kept they are reused
    assert (default_taken, taken) == ("None", "True")
    assert default_faults > 20 * 250
    assert faults < default_faults / 10
