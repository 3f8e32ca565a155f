"""Atomic output folders: build next to the target, then swap it in (no partial outputs)."""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from rotonly_cli.errors import InputError


def ordinary_permissions(path: Path) -> None:
    """Give a folder made by ``mkdtemp`` (mode 0700) the permissions of an ordinary one."""
    umask = os.umask(0)
    os.umask(umask)
    Path(path).chmod(0o777 & ~umask)


def make_staging_dir(target: Path) -> Path:
    """An empty folder beside ``target`` (same file system, so the final rename is atomic)."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    ordinary_permissions(staging)
    return staging


def check_replaceable(target: Path, allowed: set[str] | frozenset[str], what: str) -> None:
    """``target`` may be absent, empty, or hold only ``allowed`` names (an earlier ``what``):
    never replace a folder rotonly did not write (e.g. a typo pointing at a project)."""
    target = Path(target)
    if not target.exists():
        return
    if not target.is_dir():
        raise InputError("exists and is not a folder", path=str(target), field="-o")
    foreign = sorted(p.name for p in target.iterdir() if p.name not in allowed)
    if foreign:
        raise InputError(f"exists and holds files that are not {what} ({', '.join(foreign[:3])}...)",
                         path=str(target), field="-o")


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
    """Yield a staging folder beside ``target``; on success it replaces ``target``, on any
    error it is removed and ``target`` is left as it was."""
    tmp = make_staging_dir(target)
    try:
        yield tmp
        replace_dir(tmp, Path(target))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
