"""A COLMAP database checked table by table before pycolmap reads it.

pycolmap trusts the database: a blob shorter than its ``rows``/``cols`` say, a parameter
count that does not fit the camera model or an unknown model id stop it with an internal
``Check failed`` message, and NaN values pass through to the maths. :func:`check_database`
reads the tables through Python's ``sqlite3``, read-only and in one read transaction, and
raises an InputError naming the file, the table and the row for every layout pycolmap would
not read (formats.md §4.1-§4.5):

* ``cameras``: a known model, a params blob of 8 bytes per parameter of that model, and
  values that make a camera (io/inputs.check_camera);
* ``images``: a UTF-8 name, a camera that exists;
* ``keypoints``: ``rows`` >= 0, ``cols`` 2, 4 or 6, a float32 blob of rows x cols;
* ``matches`` / ``two_view_geometries``: a pair id of two images (smaller id first),
  ``cols`` 2, a uint32 blob of rows x 2; a known ``config``; F, E, H of 9 float64 (or
  none), ``qvec`` / ``tvec`` of 4 / 3 finite float64 (or none; COLMAP 3.8 writes zeros
  for "not estimated"),
  ``camera1`` / ``camera2`` (pycolmap 4.2) in COLMAP's camera blob layout.

Values that need the blobs themselves (finite keypoints) are checked by the reader on what
pycolmap returns.

An input may be written by another process meanwhile (COLMAP's feature extractor or matcher,
issue 53); rotonly never writes to it and reads a consistent state of it:

* a rollback-journal database (COLMAP 3.x's, rotonly's own) is read under SQLite's locks
  (``mode=ro``, no lock file or journal is made): a writer that holds its lock for more than
  :data:`BUSY_TIMEOUT_S` ends the run with exit 1, "database is locked by another process"
  (:class:`~rotonly_cli.errors.InputLockedError`), and the private copy the reader works on
  is made by SQLite's backup, under a shared lock (:func:`snapshot_database`). A hot journal
  (a writer killed mid-transaction) is rolled back in the private copy, never in the input.
  Opened ``immutable`` (as before issue 53), a database whose writer had already written
  some pages read as "malformed";
* a WAL database is read ``immutable`` (a reader would otherwise make -wal / -shm files
  beside it): its file holds committed pages only, and its -wal, copied beside the private
  copy, is checked there.
"""

from __future__ import annotations

import errno
import os
import shutil
import sqlite3
import struct
import tempfile
from contextlib import closing
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError, InputLockedError
from rotonly_cli.io import atomic
from rotonly_cli.io.colmap.cameras import check_colmap_camera, colmap_camera_models
from rotonly_cli.io.detect import is_sqlite
from rotonly_cli.io.inputs import check_regular_file

PathLike = str | os.PathLike

# Tables read_database needs (formats.md §4.1).
REQUIRED_TABLES = ("cameras", "images", "keypoints", "two_view_geometries")
#: COLMAP's kMaxNumImages: pair_id = K * image_id1 + image_id2 with image_id1 < image_id2 (§4.3)
PAIR_ID_FACTOR = 2147483647
#: TwoViewGeometry configurations of COLMAP 3.8 and pycolmap 4.2 (formats.md §4.5)
TWO_VIEW_CONFIGS = range(0, 10)
KEYPOINT_COLUMNS = (2, 4, 6)
_CAMERA_BLOB_HEAD = struct.Struct("<IiQQBQ")  # camera_id, model, width, height, prior flag, num params


#: seconds a read of an input database waits for another process's write lock to be released
#: (a COLMAP writer commits in well under a second), then gives up (InputLockedError, exit 1)
BUSY_TIMEOUT_S = 10.0
#: sqlite3 extended result codes: a lock held by another connection; a hot journal (a writer died
#: mid-transaction) that a read-only connection may not roll back
_SQLITE_BUSY, _SQLITE_READONLY_ROLLBACK = 5, 776
#: SQLite's primary result codes (an extended code's low byte) of a write that failed
_SQLITE_IOERR, _SQLITE_FULL = 10, 13


def is_wal(path: PathLike) -> bool:
    """Whether the database file is in WAL mode (header bytes 18-19, the file format's read
    and write versions: 2 for WAL, 1 for a rollback journal)."""
    with open(path, "rb") as stream:
        header = stream.read(20)
    return len(header) == 20 and header[18] == 2


def _locked(exc: sqlite3.Error, shown: str) -> InputLockedError | None:
    if getattr(exc, "sqlite_errorcode", None) == _SQLITE_BUSY or "database is locked" in str(exc):
        return InputLockedError(f"database is locked by another process (waited {BUSY_TIMEOUT_S:g} s for its "
                                "write to end); run again when it is done", path=shown)
    return None


def _copy_not_written(exc: sqlite3.Error, copy: Path) -> OSError | None:
    """The OSError of a snapshot whose copy could not be written: SQLite reports a full disk
    as SQLITE_FULL, or as an I/O error on a file system with no room left; None for anything
    else (the input's own errors)."""
    code = getattr(exc, "sqlite_errorcode", None)  # Python 3.11+; 3.10 has the message only
    primary = None if code is None else code & 0xFF
    if primary == _SQLITE_FULL or (code is None and "database or disk is full" in str(exc)) or \
            (primary == _SQLITE_IOERR and atomic.disk_full(copy.parent)):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(copy))
    return None


def _hot_journal(exc: sqlite3.Error) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)  # Python 3.11+; 3.10 has the message only
    return code == _SQLITE_READONLY_ROLLBACK or (code is None and "attempt to write a readonly database" in str(exc))


def _connect(path: Path, options: str) -> sqlite3.Connection:
    connection = sqlite3.connect(f"{path.resolve().as_uri()}?{options}", uri=True, timeout=BUSY_TIMEOUT_S,
                                 isolation_level=None)
    connection.text_factory = bytes
    return connection


def check_database(path: PathLike, shown: PathLike | None = None, is_input: bool = True) -> Path:
    """InputError unless ``path`` is a regular SQLite file holding COLMAP's tables in a layout
    pycolmap reads (module docstring). ``shown``: the path named in errors (the input, when
    ``path`` is its private copy); ``is_input``: another process may be writing it, and
    nothing may be made beside it (module docstring); a private copy is opened normally, so
    that its ``-wal`` is read. InputLockedError when a writer holds the input locked longer
    than :data:`BUSY_TIMEOUT_S`."""
    path = Path(path)
    shown = str(path if shown is None else shown)
    check_sqlite_file(path, shown)
    wal = is_input and is_wal(path)
    try:
        connection = _connect(path, "mode=ro&immutable=1" if wal else "mode=ro")
    except sqlite3.Error as exc:
        raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
    try:
        connection.execute("BEGIN")  # one read transaction: the tables as of one moment
        _Tables(connection, shown).check()
    except sqlite3.Error as exc:
        locked = _locked(exc, shown)
        if locked is not None:
            raise locked from None
        if not (is_input and _hot_journal(exc)):
            raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
    else:
        return path
    finally:
        connection.close()
    with tempfile.TemporaryDirectory(prefix="rotonly-db-") as scratch:  # a hot journal: check the rolled-back copy
        copy = Path(scratch) / "database.db"
        snapshot_database(path, copy, shown)
        check_database(copy, shown=shown, is_input=False)
    return path


def check_sqlite_file(path: PathLike, shown: PathLike | None = None) -> Path:
    """InputError unless ``path`` is a regular file starting with SQLite's magic."""
    path = Path(path)
    info = check_regular_file(path)
    if info.st_size == 0 or not is_sqlite(path):
        raise InputError("not an SQLite file (expected a COLMAP database)", path=str(path if shown is None else shown))
    return path


def snapshot_database(path: PathLike, copy: PathLike, shown: PathLike | None = None) -> None:
    """A consistent copy of the input database ``path`` at ``copy`` (a new file), the input
    untouched: WAL, the file and its -wal copied as they are; a rollback journal, SQLite's
    backup under a shared lock (a writer's uncommitted pages are never read;
    InputLockedError past :data:`BUSY_TIMEOUT_S`), or, behind a hot journal, the file and
    the journal copied and the journal rolled back in the copy. OSError: the copy could not
    be written."""
    path, copy = Path(path), Path(copy)
    shown = str(path if shown is None else shown)
    if is_wal(path):
        shutil.copyfile(path, copy)
        wal = Path(f"{path}-wal")  # committed-but-not-checkpointed pages
        if wal.is_file():
            check_regular_file(wal)
            shutil.copyfile(wal, f"{copy}-wal")
        return
    for _ in range(3):  # a hot journal that another reader rolls back meanwhile: again
        try:
            with closing(_connect(path, "mode=ro")) as source, closing(sqlite3.connect(str(copy))) as target:
                source.backup(target)  # every page in one step: one read transaction of the source
            return
        except sqlite3.Error as exc:
            copy.unlink(missing_ok=True)
            not_written = _copy_not_written(exc, copy)
            if not_written is not None:
                raise not_written from None
            locked = _locked(exc, shown)
            if locked is not None:
                raise locked from None
            if not _hot_journal(exc):
                raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
        try:
            shutil.copyfile(path, copy)
            shutil.copyfile(f"{path}-journal", f"{copy}-journal")
        except FileNotFoundError:  # rolled back meanwhile by another process
            continue
        try:
            with closing(sqlite3.connect(str(copy))) as rolled_back:
                rolled_back.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()  # rolls the journal back
            return
        except sqlite3.Error as exc:
            not_written = _copy_not_written(exc, copy)
            if not_written is not None:
                raise not_written from None
            raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
    raise InputLockedError("database keeps changing (its writers keep dying mid-transaction?)", path=shown)


class _Tables:
    def __init__(self, connection: sqlite3.Connection, path: str):
        self.connection = connection
        self.path = path
        self.models = colmap_camera_models()

    def fail(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field)

    def rows(self, sql: str):
        return self.connection.execute(sql)

    def columns(self, table: str) -> set[str]:
        return {row[1].decode() if isinstance(row[1], bytes) else row[1]
                for row in self.rows(f"PRAGMA table_info({table})")}

    def check(self) -> None:
        tables = {row[0].decode() for row in self.rows("SELECT name FROM sqlite_master WHERE type = 'table'")}
        for table in REQUIRED_TABLES:
            if table not in tables:
                raise self.fail(table, "COLMAP database without this table")
        cameras = self.cameras()
        images = self.images(cameras)
        self.keypoints(images)
        if "matches" in tables:
            self.pair_blobs("matches", images)
        self.pair_blobs("two_view_geometries", images)
        self.geometries()

    def integer(self, value, field: str, what: str, low: int = 0, high: int = 2 ** 31 - 1) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise self.fail(field, f"{what} {_shown(value)}: expected an integer in [{low}, {high}]")
        return value

    def cameras(self) -> dict[int, str]:
        cameras = {}
        for camera_id, model, width, height, params in self.rows(
                "SELECT camera_id, model, width, height, params FROM cameras"):
            field = f"cameras: camera {_shown(camera_id)}"
            self.integer(camera_id, field, "camera_id")
            if isinstance(model, bool) or model not in self.models:
                raise self.fail(field, f"unknown camera model id {_shown(model)}")
            name, num_params = self.models[model][:2]
            if not isinstance(params, bytes) or len(params) != 8 * num_params:
                size = "no params blob" if params is None else f"params blob of {_size(params)}"
                raise self.fail(field, f"{size}, expected {8 * num_params} bytes ({name}: {num_params} float64)")
            check_colmap_camera(self.path, field, name, width, height, np.frombuffer(params, dtype="<f8"))
            cameras[camera_id] = name
        return cameras

    def images(self, cameras: dict[int, str]) -> set[int]:
        images = set()
        for image_id, name, kind, camera_id in self.rows("SELECT image_id, name, typeof(name), camera_id FROM images"):
            field = f"images: image {_shown(image_id)}"
            self.integer(image_id, field, "image_id")
            if kind != b"text":
                raise self.fail(field, f"name {_shown(name)} is {kind.decode()}: expected text")
            try:
                name.decode("utf-8")
            except UnicodeDecodeError:
                raise self.fail(field, f"name {_shown(name)}: not UTF-8") from None
            if camera_id not in cameras:
                raise self.fail(field, f"camera {_shown(camera_id)} is not in the cameras table")
            images.add(image_id)
        return images

    def keypoints(self, images: set[int]) -> None:
        for image_id, rows, cols, kind, size in self.rows(
                "SELECT image_id, rows, cols, typeof(data), length(data) FROM keypoints"):
            if image_id not in images:
                continue  # never read
            field = f"keypoints of image {image_id}"
            self.blob(field, rows, cols, kind, size, KEYPOINT_COLUMNS, 4)

    def blob(self, field: str, rows, cols, kind: bytes, size, columns: tuple[int, ...], item_size: int) -> None:
        """A ``rows`` x ``cols`` blob of ``item_size``-byte values (none when ``rows`` is 0)."""
        self.integer(rows, field, "rows")
        if isinstance(cols, bool) or cols not in columns:
            raise self.fail(field, f"cols {_shown(cols)}: expected {' or '.join(map(str, columns))}")
        if kind not in (b"blob", b"null") or (kind == b"null" and rows):
            raise self.fail(field, f"data is {kind.decode()}, expected a blob of {rows} x {cols} values")
        expected = rows * cols * item_size
        if (size or 0) != expected:
            raise self.fail(field, f"blob of {size or 0} bytes, expected {expected}")

    def pair(self, table: str, pair_id, images: set[int]) -> str:
        field = f"{table}: pair_id {_shown(pair_id)}"
        self.integer(pair_id, field, "pair_id", high=2 ** 63 - 1)
        first, second = divmod(pair_id, PAIR_ID_FACTOR)
        if not first < second:
            raise self.fail(field, f"encodes images ({first}, {second}): the smaller id must come first")
        for image_id in (first, second):
            if image_id not in images:
                raise self.fail(field, f"pair ({first}, {second}) refers to image {image_id}, not in the images table")
        return f"{table} of pair ({first}, {second})"

    def pair_blobs(self, table: str, images: set[int]) -> None:
        for pair_id, rows, cols, kind, size in self.rows(
                f"SELECT pair_id, rows, cols, typeof(data), length(data) FROM {table}"):
            self.blob(self.pair(table, pair_id, images), rows, cols, kind, size, (2,), 4)

    def geometries(self) -> None:
        table = "two_view_geometries"
        optional = [c for c in ("camera1", "camera2") if c in self.columns(table)]
        sizes = ", ".join(f"length({c}), typeof({c})" for c in ("F", "E", "H"))
        for row in self.rows(f"SELECT pair_id, config, {sizes}, qvec, tvec"
                             f"{''.join(', ' + c for c in optional)} FROM {table}"):
            pair_id, config = row[:2]
            first, second = divmod(pair_id, PAIR_ID_FACTOR)
            field = f"{table} of pair ({first}, {second})"
            if isinstance(config, bool) or config not in TWO_VIEW_CONFIGS:
                raise self.fail(field, f"config {_shown(config)}: not a TwoViewGeometry configuration (0-9)")
            for k, name in enumerate(("F", "E", "H")):
                size, kind = row[2 + 2 * k: 4 + 2 * k]
                if kind not in (b"blob", b"null") or (size or 0) not in (0, 72):
                    raise self.fail(field, f"{name}: {_size(size)} of {kind.decode()}, expected 72 (3 x 3 float64)")
            qvec, tvec = row[8:10]
            self.vector(field, "qvec", qvec, 4)
            self.vector(field, "tvec", tvec, 3)
            if (qvec is None) != (tvec is None):
                raise self.fail(field, "qvec and tvec: one is set, the other not")
            for name, blob in zip(optional, row[10:]):
                self.camera_blob(f"{field}: {name}", blob)

    def vector(self, field: str, name: str, blob, length: int) -> None:
        if blob is None:
            return
        if not isinstance(blob, bytes) or len(blob) != 8 * length:
            raise self.fail(field, f"{name}: {_size(blob)}, expected {8 * length} ({length} float64)")
        values = np.frombuffer(blob, dtype="<f8")
        if not np.all(np.isfinite(values)):
            raise self.fail(field, f"{name} ({', '.join(map(str, values))}): not finite")

    def camera_blob(self, field: str, blob) -> None:
        """COLMAP's CameraToBlob layout (formats.md §4.2), NULL when not estimated."""
        if blob is None:
            return
        head = _CAMERA_BLOB_HEAD.size
        if not isinstance(blob, bytes) or len(blob) < head:
            raise self.fail(field, f"{_size(blob)}: shorter than a camera ({head} bytes and the params)")
        _, model, width, height, _, num_params = _CAMERA_BLOB_HEAD.unpack_from(blob)
        if model not in self.models or self.models[model][1] != num_params:
            raise self.fail(field, f"camera model {model} with {num_params} params: not a COLMAP camera")
        if len(blob) != head + 8 * num_params:
            raise self.fail(field, f"{_size(blob)}, expected {head + 8 * num_params}")
        check_colmap_camera(self.path, field, self.models[model][0], width, height,
                            np.frombuffer(blob, dtype="<f8", offset=head))


def _size(blob) -> str:
    if isinstance(blob, int):
        return f"{blob} bytes"
    return "nothing" if blob is None else f"{len(blob)} bytes" if isinstance(blob, bytes) else repr(blob)


def _shown(value) -> str:
    text = repr(value.decode("utf-8", errors="backslashreplace") if isinstance(value, bytes) else value)
    return text if len(text) <= 40 else f"{text[:30]}... ({len(text)} characters)"
