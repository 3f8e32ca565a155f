"""Every file and folder rotonly writes goes through here: built beside the target, then
renamed into place, so a failed or interrupted write never leaves a partial output.

* :func:`write_bytes` / :func:`write_text`: one file (temporary sibling, ``os.replace``);
* :func:`file_path`: a temporary sibling path for writers that want a file name (numpy,
  SQLite), renamed over the target when the block ends without error;
* :func:`staging_dir`: a folder that replaces the target folder as a whole;
* :func:`filling_dir`: a folder whose files are moved into the target folder one by one
  (a new target appears by one rename): the writers of a project or a model into a
  folder that may hold other files.

Temporary files and folders get the permissions of ordinary ones (``mkstemp`` makes 0600,
``mkdtemp`` 0700), so outputs look as if ``open``/``mkdir`` had made them.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rotonly_cli.errors import InputError

PathLike = str | os.PathLike


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def ordinary_permissions(path: PathLike) -> None:
    """Give a file or a folder made by ``mkstemp`` / ``mkdtemp`` the permissions ``open`` /
    ``mkdir`` would have given it."""
    path = Path(path)
    path.chmod((0o777 if path.is_dir() else 0o666) & ~_umask())


def _temporary_sibling(target: Path, suffix: str) -> Path:
    """A free file name beside ``target`` (same file system: the final rename is atomic)."""
    handle, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    os.close(handle)
    return Path(name)


@contextmanager
def file_path(path: PathLike, suffix: str = ".tmp", create: bool = True,
              sidecars: Iterable[str] = ()) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (an empty file, or no file with ``create``
    False, for writers that refuse an existing one); when the block ends without error it
    replaces ``path``. ``sidecars``: suffixes of files a writer may leave beside it (SQLite's
    ``-journal``), removed in any case."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = _temporary_sibling(path, suffix)
    if not create:
        temporary.unlink()
    try:
        yield temporary
        ordinary_permissions(temporary)
        os.replace(temporary, path)
    finally:
        for leftover in (temporary, *(Path(f"{temporary}{s}") for s in sidecars)):
            leftover.unlink(missing_ok=True)


def write_bytes(path: PathLike, payload: bytes | Iterable[bytes]) -> None:
    """Write ``payload`` (bytes, or consecutive pieces of it) to ``path`` atomically."""
    with file_path(path) as temporary, open(temporary, "wb") as stream:
        stream.writelines([payload] if isinstance(payload, bytes) else payload)


def write_text(path: PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def make_staging_dir(target: PathLike) -> Path:
    """An empty folder beside ``target`` (same file system, so the final rename is atomic)."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    ordinary_permissions(staging)
    return staging


def check_replaceable(target: PathLike, allowed: set[str] | frozenset[str], what: str) -> None:
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


def replace_dir(staging: PathLike, target: PathLike) -> None:
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
def staging_dir(target: PathLike) -> Iterator[Path]:
    """Yield a staging folder beside ``target``; on success it replaces ``target``, on any
    error it is removed and ``target`` is left as it was."""
    tmp = make_staging_dir(target)
    try:
        yield tmp
        replace_dir(tmp, Path(target))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def filling_dir(target: PathLike) -> Iterator[Path]:
    """Yield a staging folder beside ``target``; on success a new ``target`` appears by one
    rename, an existing one receives the staged files one rename each (other files in it
    stay). The staging folder is removed in any case."""
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise InputError("exists and is not a directory", path=str(target))
    staging = make_staging_dir(target)
    try:
        yield staging
        if not target.exists():
            os.replace(staging, target)
            return
        if not target.is_dir():
            raise InputError("exists and is not a directory", path=str(target))
        for staged in sorted(staging.iterdir()):
            os.replace(staged, target / staged.name)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
