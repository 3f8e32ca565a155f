"""The stages of the chain (chain/stages.py runs them; each module's docstring says what it does)."""

from __future__ import annotations

from collections.abc import Iterable

#: the stages of `rotonly run`, in chain order (chain/stages.py runs them)
STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


def listed(items: Iterable[str], max_shown: int = 8) -> str:
    """The first ``max_shown`` of ``items`` joined by commas, then " ..." if there are more: how
    the run's messages name views and edges."""
    items = list(items)
    return ", ".join(items[:max_shown]) + (" ..." if len(items) > max_shown else "")
