"""pytest set-up shared by every test.

The tests mirror the package (tests/geometry/ tests rotonly_cli/geometry/, ...); test file
names are unique across folders (pytest's default import mode needs that without
__init__.py files). This file puts its folder on sys.path (pytest's rootdir conftest), so
every test imports the shared helpers as ``from helpers import ...``: the bundled fixtures'
path (the tests read data_fixtures/ only) and the simulated scenes of the geometry tests.
"""

import signal

import pytest


@pytest.fixture(autouse=True)
def _sigint_handler_restored():
    """Each test starts and ends with the Ctrl-C handler it found, and with no command's
    outcome marked written: ``cli.console_main``, called in this process by some tests, installs
    the CLI's handler for the rest of the process, and a command that put its output in place
    leaves runtime/interrupts' flag set; together they would ignore Ctrl-C in the tests after it."""
    from rotonly_cli.runtime import interrupts

    handler = signal.getsignal(signal.SIGINT)
    yield
    if handler is not None:
        signal.signal(signal.SIGINT, handler)
    interrupts._WRITTEN[0] = False
