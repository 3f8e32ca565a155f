"""Typed errors. The CLI maps them to exit codes (architecture.md "Exit codes")."""

from __future__ import annotations


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
