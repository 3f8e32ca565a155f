"""A COLMAP database checked table by table before pycolmap reads it.

pycolmap trusts the database: a blob shorter than its ``rows``/``cols`` say, a parameter
count that does not fit the camera model or an unknown model id stop it with an internal
``Check failed`` message, and NaN values pass through to the maths. :func:`check_database`
reads the tables through Python's ``sqlite3`` (read-only; ``immutable`` for an input, so
that not even a lock file appears beside it) and raises an InputError naming the file, the
table and the row for every layout pycolmap would not read (formats.md §4.1-§4.5):

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
"""

from __future__ import annotations

import os
import sqlite3
import struct
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
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


def check_database(path: PathLike, shown: PathLike | None = None, immutable: bool = True) -> Path:
    """InputError unless ``path`` is a regular SQLite file holding COLMAP's tables in a layout
    pycolmap reads (module docstring). ``shown``: the path named in errors (the input, when
    ``path`` is its private copy); ``immutable``: open without any lock or sidecar file
    (an input; a private copy is opened normally so that its ``-wal`` is read)."""
    path = Path(path)
    shown = str(path if shown is None else shown)
    info = check_regular_file(path)
    if info.st_size == 0 or not is_sqlite(path):
        raise InputError("not an SQLite file (expected a COLMAP database)", path=shown)
    options = "mode=ro&immutable=1" if immutable else "mode=ro"
    try:
        connection = sqlite3.connect(f"{path.resolve().as_uri()}?{options}", uri=True)
    except sqlite3.Error as exc:
        raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
    connection.text_factory = bytes
    try:
        _Tables(connection, shown).check()
    except sqlite3.Error as exc:
        raise InputError(f"unreadable SQLite database ({exc})", path=shown) from None
    finally:
        connection.close()
    return path


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
