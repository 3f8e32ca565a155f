"""The command line of the rotonly command this process runs, for the records a run writes
(reports/run.json ``command``, report.html). Set by cli.main for the length of the command;
None for callers of the Python API."""

from __future__ import annotations

import shlex
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

_arguments: list[str] | None = None


@contextmanager
def invoked_with(arguments: Sequence[str]) -> Iterator[None]:
    """Within the block, :func:`command_line` is ``rotonly ARGUMENTS``."""
    global _arguments
    previous, _arguments = _arguments, [str(a) for a in arguments]
    try:
        yield
    finally:
        _arguments = previous


def command_line() -> str | None:
    """``rotonly ARGUMENTS`` as a shell would take it (quoted where needed), or None outside a command."""
    return None if _arguments is None else shlex.join(["rotonly", *_arguments])
