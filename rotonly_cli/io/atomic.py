"""Atomic output folders: build next to the target, then swap it in (no partial outputs)."""

from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path


def replace_dir(staging: Path, target: Path) -> None:
    """Move the finished ``staging`` folder to ``target``, keeping any old ``target`` until
    the new one is in place."""
    staging, target = Path(staging), Path(target)
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
        old.rmdir()
        target.rename(old)
        staging.rename(target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staging.rename(target)


@contextmanager
def staging_dir(target: Path):
    """Yield a temp folder beside ``target``; on success it replaces ``target``, on any
    error it is removed and ``target`` is left as it was."""
    target = Path(target)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        yield tmp
        replace_dir(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
