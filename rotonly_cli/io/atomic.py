"""Every file and folder rotonly writes goes through here: built beside the target, then
renamed into place, so a failed or interrupted write never leaves a partial output.

* :func:`write_bytes` / :func:`write_text`: one file (temporary sibling, ``os.replace``);
* :func:`file_path`: a temporary sibling path for writers that want a file name (numpy,
  SQLite), renamed over the target when the block ends without error;
* :class:`Staging` / :func:`staging_dir`: a folder that replaces the target folder as a
  whole, in one atomic exchange, and whose leftovers after a kill the next run removes;
* :func:`filling_dir`: a folder whose files are moved into the target folder one by one
  (a new target appears by one rename): the writers of a project or a model into a
  folder that may hold other files.

Temporary files and folders get the permissions of ordinary ones (``mkstemp`` makes 0600,
``mkdtemp`` 0700), so outputs look as if ``open``/``mkdir`` had made them.

Ctrl-C during :meth:`Staging.commit` is deferred to its end (:func:`deferred_interrupts`): the
target is never left half-committed with the staging folder half-removed, and the caller learns
the outcome (``committed``) before the Ctrl-C is delivered.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rotonly_cli.errors import InputError, write_error

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


def disk_full(path: PathLike) -> bool:
    """Whether the file system of ``path`` has (almost) no room left: what a writer that
    does not report its errors (pycolmap's C++ streams) most likely ran into."""
    space = os.statvfs(path)
    free = space.f_bavail * space.f_frsize
    return free < max(2 ** 20, 0.001 * space.f_blocks * space.f_frsize)


def unreported_write_error(path: PathLike, what: str) -> OSError:
    """The OSError a silent writer should have raised under ``path``: ENOSPC on a full file
    system, else EIO with ``what`` went wrong."""
    if disk_full(path):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return OSError(errno.EIO, what, str(path))


@contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Ctrl-C (SIGINT) held back while the block runs, then delivered again (``raise_signal``) to
    the handler in place before it: the block's work is done, or its error raised, first (the
    KeyboardInterrupt then carries that error as its context). Only in the main thread, where
    Python runs its signal handlers; elsewhere, or under a handler not set from Python, a no-op."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda number, frame: received.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received:
            signal.raise_signal(signal.SIGINT)


# ============================================================================ staging folders

#: the file that marks a staging folder as rotonly's; locked (flock) by the run that uses it
STAGING_MARKER = ".rotonly-staging"
#: descriptors holding the markers' locks in this process. A forked child closes its copies at
#: once (:func:`_close_locks_in_child`): a flock belongs to the open file, so a child that kept
#: one, and outlived a killed run, would keep the run's staging folder locked (never removed)
_LOCKS: set[int] = set()


def _close_locks_in_child() -> None:
    for handle in _LOCKS:
        try:
            os.close(handle)
        except OSError:
            pass
    _LOCKS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_locks_in_child)
_AT_FDCWD = -100
_RENAME_NOREPLACE, _RENAME_EXCHANGE = 1, 2


def _libc_renameat2():
    try:
        return ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):  # not Linux, or glibc < 2.28
        return None


_renameat2_function = _libc_renameat2() if sys.platform.startswith("linux") else None


def _renameat2(source: Path, destination: Path, flags: int) -> bool:
    """Linux ``renameat2(source, destination, flags)``; False where the system or the file
    system does not have it (the caller then falls back on ``os.rename``)."""
    if _renameat2_function is None:
        return False
    if _renameat2_function(_AT_FDCWD, os.fsencode(source), _AT_FDCWD, os.fsencode(destination), flags) == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(error, os.strerror(error), str(destination))


def _create_parents(folder: Path) -> list[Path]:
    """``mkdir -p folder``; the folders made, outermost first. InputError (-o) if an
    existing ancestor is not a folder."""
    missing = []
    while not folder.exists():
        if os.path.lexists(folder):  # a dangling symbolic link
            raise InputError("is a broken symbolic link", path=str(folder), field="-o")
        missing.append(folder)
        folder = folder.parent
    if not folder.is_dir():
        raise InputError("is not a folder", path=str(folder), field="-o")
    for made in reversed(missing):
        try:
            made.mkdir()
        except FileExistsError:  # made by someone else meanwhile
            missing.remove(made)
    return list(reversed(missing))


class Staging:
    """A folder beside ``target`` that becomes it, for writers that must never leave a
    partial ``target``: ``.{target.name}.XXXXXXXX.tmp/`` holding ``new/`` (the future
    target), ``scratch/`` (private files of the run: never moved) and :data:`STAGING_MARKER`,
    which names the target and stays locked (``flock``) while this process lives. A run that
    is killed leaves the folder with an unlocked marker (its forked children close their copies
    of the lock at once), or locked by a process that outlived it; the next staging of the same
    target removes it (:func:`remove_stale`). Folders without the marker are never touched.

    :meth:`commit` puts ``new/`` at ``target`` so that at every instant ``target`` is either
    the old folder or the new one: ``renameat2(RENAME_EXCHANGE)`` swaps them in one step
    (Linux; the old one then lies in the staging folder and goes with it), a new ``target``
    appears by ``renameat2(RENAME_NOREPLACE)``. Where the file system has no ``renameat2``,
    two renames keep the old folder inside the staging folder in between, and
    :func:`remove_stale` puts it back if the run died there. Concurrent runs into one target
    each swap their complete folder in: the last one stays, none is stranded.

    Parents of ``target`` made for it are removed again when the staging is discarded."""

    def __init__(self, target: PathLike):
        self.target = Path(os.path.abspath(target))
        self.committed = False
        self.lock = None
        self.created_parents: list[Path] = []
        self.owner = os.getpid()  # a forked child inherits the object, never the folder's removal
        try:
            # Ctrl-C deferred while the folder is made: raised inside mkdtemp, it would leave a
            # folder whose name this object never learnt, so that discard() could not remove it
            with deferred_interrupts():
                self._make()
        except OSError as exc:
            self.discard()
            raise write_error(exc, self.target) from None
        except BaseException:
            self.discard()
            raise

    def _make(self) -> None:
        self.created_parents = _create_parents(self.target.parent)
        if self.target.is_dir() and os.stat(self.target).st_dev != os.stat(self.target.parent).st_dev:
            raise InputError("is a mount point: it cannot be replaced in one step (give a folder inside it)",
                             path=str(self.target), field="-o")
        remove_stale(self.target)
        for _ in range(10):
            self.root = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.", suffix=".tmp", dir=self.target.parent))
            try:
                self.lock = _locked_marker(self.root, self.target.name)
                break
            except FileNotFoundError:  # another run's remove_stale took it before its marker existed
                continue
        else:
            raise OSError(errno.EBUSY, "the staging folder keeps vanishing (other runs into it?)", str(self.target))
        self.new = self.root / "new"
        self.scratch = self.root / "scratch"
        self.new.mkdir()
        self.scratch.mkdir()

    def commit(self, check: Callable[[Path], None] | None = None,
               committed: Callable[[], None] | None = None) -> None:
        """Put ``new/`` at the target (class docstring), then discard the rest. ``check``:
        called on an existing target just before it is replaced (it may raise); ``committed``:
        called once the target is the new one. Ctrl-C is deferred until all of this is done
        (:func:`deferred_interrupts`): then the new target is in place, the staging folder
        gone, and ``committed`` has told the caller (the CLI then exits 0 under a Ctrl-C)."""
        with deferred_interrupts():
            self._exchange(check)
            self.committed = True
            if committed is not None:
                committed()
            self.discard()

    def _exchange(self, check: Callable[[Path], None] | None) -> None:
        for _ in range(100):  # a concurrent run may create or swap the target in between
            if not os.path.lexists(self.target):
                try:
                    if not _renameat2(self.new, self.target, _RENAME_NOREPLACE):
                        os.rename(self.new, self.target)
                    break
                except FileExistsError:
                    continue
            if check is not None:
                check(self.target)
            try:
                if not _renameat2(self.new, self.target, _RENAME_EXCHANGE):
                    os.rename(self.target, self.root / "old")
                    os.rename(self.new, self.target)
                break
            except FileNotFoundError:
                continue
        else:
            raise OSError(errno.EBUSY, "the target keeps changing (other runs into it?)", str(self.target))

    def discard(self) -> None:
        """Remove the staging folder (and the parents made for it, unless committed); in the
        process that made it only."""
        if os.getpid() != self.owner:
            return
        root = getattr(self, "root", None)
        if root is not None:
            shutil.rmtree(root, ignore_errors=True)
        if self.lock is not None:
            _LOCKS.discard(self.lock)
            os.close(self.lock)
            self.lock = None
        if not self.committed:
            for parent in reversed(self.created_parents):  # innermost first
                try:
                    parent.rmdir()
                except OSError:  # not empty: someone else writes there too
                    break
            self.created_parents = []


def _locked_marker(root: Path, target_name: str) -> int:
    """Create ``root``/STAGING_MARKER already locked: it is written and locked under a
    temporary name first, so no other run ever sees it unlocked while this one lives."""
    handle, name = tempfile.mkstemp(prefix=".lock.", dir=root)
    _LOCKS.add(handle)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        marker = {"target": target_name, "pid": os.getpid(), **_process_identity(os.getpid())}
        os.write(handle, json.dumps(marker).encode() + b"\n")
        os.rename(name, root / STAGING_MARKER)
    except BaseException:
        _LOCKS.discard(handle)
        os.close(handle)
        raise
    return handle


def _process_identity(pid: int) -> dict:
    """What tells process ``pid`` from a later one given the same number: its start time (clock
    ticks since boot, /proc/PID/stat field 22) and its PID namespace; {} where /proc does not
    tell."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            fields = stat.read().rsplit(b")", 1)[1].split()
        return {"started": int(fields[19]), "pid_namespace": os.readlink(f"/proc/{pid}/ns/pid")}
    except (OSError, IndexError, ValueError):
        return {}


def _run_is_dead(marker: dict) -> bool:
    """Whether the run a marker names is gone although someone holds its lock: a process it
    forked that outlived it (rotonly's own die with it: runtime/parallel). Judged only where
    the marker's PID namespace is this one's, by the PID's start time (a PID is reused)."""
    pid, started = marker.get("pid"), marker.get("started")
    if not isinstance(pid, int) or not isinstance(started, int):
        return False
    mine = _process_identity(os.getpid())
    if not mine or marker.get("pid_namespace") != mine["pid_namespace"]:
        return False
    return _process_identity(pid).get("started") != started


#: what follows ``.{target name}.`` in a staging folder's name (tempfile.mkdtemp's 8 characters)
_STAGING_NAME = re.compile(r"[a-z0-9_]{8}\.tmp")


@contextmanager
def _unlocked(path: Path) -> Iterator[int | None]:
    """A descriptor of ``path`` holding its ``flock``, or None when ``path`` cannot be opened
    or another process holds the lock (the run that made it is alive)."""
    try:
        handle = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        yield None
        return
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield None
            return
        yield handle
    finally:
        os.close(handle)


def _remove_unmarked(folder: Path) -> bool:
    """Remove a staging folder that has no marker yet, if its run is dead: a kill between
    ``mkdtemp`` and the marker's rename (:func:`_locked_marker`) leaves it empty or holding
    only the marker's temporary ``.lock.*`` file, unlocked. A live run that loses its folder
    in that instant makes a new one (:class:`Staging`). Anything else in it: not touched."""
    try:
        names = os.listdir(folder)
    except OSError:
        return False
    if any(not name.startswith(".lock.") for name in names):
        return False
    for name in names:
        with _unlocked(folder / name) as handle:
            if handle is None:
                return False
            try:
                os.unlink(folder / name)
            except OSError:
                return False
    try:
        os.rmdir(folder)
    except OSError:
        return False
    return True


def remove_stale(target: PathLike) -> list[Path]:
    """Remove the staging folders of ``target`` left by runs that died (module docstring of
    :class:`Staging`): siblings ``.{name}.*.tmp`` whose marker names ``target`` and is not
    locked, or is locked but names a run that is gone (:func:`_run_is_dead`). A folder holding
    the old target of a run that died between its two fallback renames gives it back first.
    Returns the folders removed."""
    target = Path(os.path.abspath(target))
    removed = []
    try:
        siblings = list(os.scandir(target.parent))
    except OSError:
        return removed
    prefix = f".{target.name}."
    for entry in siblings:
        if not (entry.name.startswith(prefix) and entry.name.endswith(".tmp")) or not entry.is_dir(
                follow_symlinks=False):
            continue
        folder = Path(entry.path)
        marker_path = folder / STAGING_MARKER
        if not os.path.lexists(marker_path):  # being made, or its run was killed while making it
            if _STAGING_NAME.fullmatch(entry.name[len(prefix):]) and _remove_unmarked(folder):
                removed.append(folder)
            continue
        with _unlocked(marker_path) as handle:
            if handle is None and not _run_is_dead(_read_marker(marker_path)):  # its run is alive
                continue
            try:
                marker = json.loads(os.read(handle, 4096) or b"{}") if handle is not None \
                    else _read_marker(marker_path)
                if not isinstance(marker, dict) or marker.get("target") != target.name:
                    continue
                old = folder / "old"
                if old.is_dir() and not os.path.lexists(target):
                    os.rename(old, target)  # the run died between its two fallback renames
                shutil.rmtree(folder, ignore_errors=True)
                removed.append(folder)
            except (OSError, ValueError):
                continue
    return removed


def _read_marker(path: Path) -> dict:
    """A marker's content without its lock ({} if unreadable): written before the marker got
    its name, so it is whole."""
    try:
        with open(path, "rb") as marker:
            content = json.loads(marker.read(4096) or b"{}")
    except (OSError, ValueError):
        return {}
    return content if isinstance(content, dict) else {}


def check_replaceable(target: PathLike, allowed: set[str] | frozenset[str], what: str) -> None:
    """``target`` may be absent, empty, or hold only ``allowed`` names (an earlier ``what``)
    and the temporary files rotonly's writers make beside them (``.<name>.XXXX<suffix>``):
    never replace a folder rotonly did not write (e.g. a typo pointing at a project)."""
    target = Path(target)
    if not os.path.lexists(target):
        return
    if not target.is_dir():
        raise InputError("exists and is not a folder", path=str(target), field="-o")
    try:
        names = [p.name for p in target.iterdir()]
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(target), field="-o") from None
    foreign = sorted(name for name in names if name not in allowed and not _is_temporary_of(name, allowed))
    if foreign:
        raise InputError(f"exists and holds files that are not {what} ({', '.join(foreign[:3])}...)",
                         path=str(target), field="-o")


def _is_temporary_of(name: str, allowed) -> bool:
    """A temporary sibling of an allowed name (:func:`file_path`, :func:`filling_dir`), left
    by a stage command that was killed."""
    return any(name.startswith(f".{entry}.") for entry in allowed)


@contextmanager
def staging_dir(target: PathLike, check: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """Yield a folder that replaces ``target`` as a whole when the block ends without error
    (:class:`Staging`; ``check`` as in :meth:`Staging.commit`); on any error it is removed
    and ``target`` is left as it was."""
    staging = Staging(target)
    try:
        yield staging.new
        staging.commit(check)
    finally:
        staging.discard()


@contextmanager
def scratch_dir(target: PathLike) -> Iterator[Path]:
    """Yield a private folder beside ``target`` (in a :class:`Staging` folder, so a killed
    run's leftovers are removed by the next one), removed when the block ends."""
    staging = Staging(target)
    try:
        yield staging.scratch
    finally:
        staging.discard()


@contextmanager
def filling_dir(target: PathLike) -> Iterator[Path]:
    """Yield a staging folder beside ``target``; on success a new ``target`` appears by one
    rename, an existing one receives the staged files one rename each (other files in it
    stay). The staging folder is removed in any case."""
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise InputError("exists and is not a directory", path=str(target))
    staging = Staging(target)
    try:
        yield staging.new
        if not target.exists():
            staging.commit()
            return
        if not target.is_dir():
            raise InputError("exists and is not a directory", path=str(target))
        for staged in sorted(staging.new.iterdir()):
            os.replace(staged, target / staged.name)
    finally:
        staging.discard()
