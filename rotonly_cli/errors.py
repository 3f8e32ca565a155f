"""Typed errors. The CLI maps them to exit codes (architecture.md "Exit codes"): bad input or
usage 2, an accuracy regression found by `rotonly eval`'s limits 3, everything rotonly reports
on purpose otherwise 1. Any other exception is a bug."""

from __future__ import annotations

import errno


class RotonlyError(Exception):
    """Base class of every error rotonly raises on purpose."""

    exit_code = 1


class InputError(RotonlyError, ValueError):
    """Bad input or usage: exit code 2. The message names the file and the field."""

    exit_code = 2

    def __init__(self, message: str, path: str | None = None, field: str | None = None):
        self.path = None if path is None else str(path)
        self.field = field
        parts = []
        if self.path:
            parts.append(self.path)
        if field:
            parts.append(field)
        prefix = ": ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class AlgorithmError(RotonlyError):
    """The algorithm could not produce a result (exit code 1)."""

    exit_code = 1


class RegressionError(RotonlyError):
    """`rotonly eval`'s regression gate: a number crossed its limit (exit code 3). The message
    is one line naming each such metric, its value and the limit (evaluation/gate.py)."""

    exit_code = 3


class OutputError(RotonlyError):
    """An output could not be written although the destination was usable when the run
    started (disk full, quota, I/O error): exit code 1. Nothing partial is left."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None):
        self.path = None if path is None else str(path)
        super().__init__(f"{path}: {message}" if path else message)


#: errno values that mean "this destination cannot be used" (usage: exit 2), as opposed to a
#: destination that ran out of room or failed while being written (exit 1)
_UNUSABLE_DESTINATION = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EEXIST, errno.EISDIR,
                         errno.ENAMETOOLONG, errno.ELOOP, errno.ENOENT}


def write_error(exc: OSError, path, field: str | None = "-o") -> RotonlyError:
    """The one-line error for an ``OSError`` raised while writing under ``path``: InputError
    (exit 2) when the destination cannot be used at all, OutputError (exit 1) otherwise."""
    reason = exc.strerror or str(exc)
    if exc.errno in _UNUSABLE_DESTINATION:
        return InputError(f"cannot write: {reason}", path=str(path), field=field)
    return OutputError(f"cannot write: {reason}", path=str(path))


class OutOfMemoryError(AlgorithmError):
    """A stage would not fit in the memory limit (predicted before it ran: runtime/memory.py),
    or ran out of memory: exit code 1, OUT as it was."""


class InputLockedError(RotonlyError):
    """The input is being written by another process (a COLMAP database under its writer's
    lock) for longer than rotonly waits: exit code 1, nothing written; run again once the
    writer is done."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None):
        self.path = None if path is None else str(path)
        super().__init__(f"{path}: {message}" if path else message)
