"""``enum.StrEnum`` on Python 3.10 too (rotonly supports 3.10; StrEnum came with 3.11)."""

from __future__ import annotations

try:
    from enum import StrEnum
except ImportError:  # Python 3.10
    from enum import Enum

    class StrEnum(str, Enum):  # type: ignore[no-redef]
        """Members are strings: equal to their value, formatted and JSON-encoded as it."""

        def __str__(self) -> str:
            return self.value

        def __format__(self, spec: str) -> str:
            return self.value.__format__(spec)

__all__ = ["StrEnum"]
