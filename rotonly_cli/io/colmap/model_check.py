"""A COLMAP sparse model checked file by file before pycolmap reads it (formats.md §4.8).

pycolmap reads a model without questions: a truncated record, an unknown camera model, a
parameter count that does not fit it, a track element pointing at an image or a keypoint
that does not exist stop it with an internal ``Check failed`` message (or worse, a value out
of range), and NaN poses pass through. :func:`check_model` walks the files in the layout
pycolmap reads (``cameras``, ``rigs``, ``frames``, ``images``, ``points3D``; ``.bin`` or
``.txt``, whichever pycolmap would pick) and raises an InputError naming the file and the
record for every one it could not read: sizes, known camera models with the right
parameter count, cameras that make sense (io/inputs.check_camera), finite poses and
keypoints, and references between the files (image -> camera, frame -> rig, image ->
frame, track element -> image and keypoint).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.colmap.cameras import check_colmap_camera, colmap_camera_models
from rotonly_cli.io.inputs import read_bytes

PathLike = str | os.PathLike
MODEL_FILES = ("cameras", "images", "points3D")
OPTIONAL_FILES = ("rigs", "frames")
SENSOR_TYPES = {"INVALID": -1, "CAMERA": 0, "IMU": 1}
_INVALID_POINT3D = 2 ** 64 - 1


@dataclass
class _Facts:
    """What later files of a model refer to."""

    cameras: set[int] = field(default_factory=set)
    rigs: set[int] = field(default_factory=set)
    framed_images: set[int] | None = None  # None: no rigs/frames (a legacy model)
    points2D: dict[int, int] = field(default_factory=dict)  # image id -> number of keypoints


def model_extension(path: PathLike) -> str | None:
    """``.bin`` or ``.txt``: the files pycolmap reads in ``path`` (binary first)."""
    for ext in (".bin", ".txt"):
        if all((Path(path) / f"{stem}{ext}").is_file() for stem in MODEL_FILES):
            return ext
    return None


def check_model(path: PathLike) -> str:
    """InputError unless the model in folder ``path`` is one pycolmap reads (module
    docstring); returns the extension read (``.bin`` or ``.txt``)."""
    path = Path(path)
    ext = model_extension(path)
    if ext is None:
        raise InputError("not a COLMAP model (needs cameras, images, points3D .bin or .txt)", path=str(path))
    facts = _Facts()
    checker = _Binary if ext == ".bin" else _Text
    for stem in ("cameras", *OPTIONAL_FILES, "images", "points3D"):
        file = path / f"{stem}{ext}"
        if stem in OPTIONAL_FILES and not os.path.lexists(file):
            continue
        getattr(checker(file), stem)(facts)
    return ext


def _fail(file: Path, where: str, message: str) -> InputError:
    return InputError(message, path=str(file), field=where)


def _check_pose(file: Path, where: str, values, what: str = "pose") -> None:
    """qw qx qy qz tx ty tz: finite, a non-zero quaternion."""
    values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise _fail(file, where, f"{what} ({', '.join(map(str, values))}): not finite")
    if not np.any(values[:4]):
        raise _fail(file, where, f"{what}: zero quaternion")


def _check_camera_values(file: Path, where: str, model: int, width, height, params) -> None:
    check_colmap_camera(str(file), where, colmap_camera_models()[model][0], width, height, params)


class _Binary:
    """The binary files (formats.md §4.8), read with a cursor that names where it stopped."""

    def __init__(self, file: Path):
        self.file = file
        self.data = read_bytes(file)
        self.offset = 0

    def take(self, layout: str, where: str) -> tuple:
        unpacker = struct.Struct("<" + layout)
        if self.offset + unpacker.size > len(self.data):
            raise _fail(self.file, where, f"truncated: {len(self.data)} bytes, the record needs "
                                          f"{self.offset + unpacker.size - len(self.data)} more")
        values = unpacker.unpack_from(self.data, self.offset)
        self.offset += unpacker.size
        return values

    def array(self, dtype: str, count: int, where: str) -> np.ndarray:
        size = np.dtype(dtype).itemsize * count
        if self.offset + size > len(self.data):
            raise _fail(self.file, where, f"truncated: {len(self.data)} bytes, the record needs "
                                          f"{self.offset + size - len(self.data)} more")
        values = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.offset)
        self.offset += size
        return values

    def records(self) -> range:
        return range(self.take("Q", "header")[0])

    def done(self) -> None:
        if self.offset != len(self.data):
            raise _fail(self.file, "end", f"{len(self.data) - self.offset} bytes after the last record")

    def cameras(self, facts: _Facts) -> None:
        models = colmap_camera_models()
        for k in self.records():
            camera_id, model, width, height = self.take("IiQQ", f"camera record {k}")
            where = f"camera {camera_id}"
            if model not in models:
                raise _fail(self.file, where, f"unknown camera model id {model}")
            params = self.array("<f8", models[model][1], where)
            _check_camera_values(self.file, where, model, width, height, params)
            facts.cameras.add(camera_id)
        self.done()

    def rigs(self, facts: _Facts) -> None:
        for k in self.records():
            rig_id, num_sensors = self.take("II", f"rig record {k}")
            where = f"rig {rig_id}"
            if num_sensors:
                self.sensor(facts, where, *self.take("iI", where))
            for _ in range(max(num_sensors - 1, 0)):
                sensor_type, sensor_id, has_pose = self.take("iIB", where)
                self.sensor(facts, where, sensor_type, sensor_id)
                if has_pose:
                    _check_pose(self.file, where, self.array("<f8", 7, where), "sensor_from_rig")
            facts.rigs.add(rig_id)
        facts.framed_images = facts.framed_images or set()
        self.done()

    def sensor(self, facts: _Facts, where: str, sensor_type: int, sensor_id: int) -> None:
        if sensor_type not in SENSOR_TYPES.values() or sensor_type < 0:
            raise _fail(self.file, where, f"unknown sensor type {sensor_type}")
        if sensor_type == SENSOR_TYPES["CAMERA"] and sensor_id not in facts.cameras:
            raise _fail(self.file, where, f"camera {sensor_id} is not in the cameras file")

    def frames(self, facts: _Facts) -> None:
        framed = facts.framed_images = facts.framed_images or set()
        for k in self.records():
            frame_id, rig_id = self.take("II", f"frame record {k}")
            where = f"frame {frame_id}"
            if rig_id not in facts.rigs:
                raise _fail(self.file, where, f"rig {rig_id} is not in the rigs file")
            _check_pose(self.file, where, self.array("<f8", 7, where), "rig_from_world")
            for _ in range(self.take("I", where)[0]):
                sensor_type, _, data_id = self.take("iIQ", where)
                if sensor_type == SENSOR_TYPES["CAMERA"]:
                    framed.add(data_id)
        self.done()

    def images(self, facts: _Facts) -> None:
        for k in self.records():
            image_id, *pose, camera_id = self.take("I7dI", f"image record {k}")
            where = f"image {image_id}"
            _check_pose(self.file, where, pose)
            _check_image(self.file, where, facts, image_id, camera_id)
            end = self.data.find(b"\0", self.offset)
            if end < 0:
                raise _fail(self.file, where, "truncated: the name has no end")
            _check_name(self.file, where, self.data[self.offset:end])
            self.offset = end + 1
            (num_points2D,) = self.take("Q", where)
            points = self.array("<f8", 3 * num_points2D, where).reshape(-1, 3)  # x, y, point3D id (bits)
            if not np.all(np.isfinite(points[:, :2])):
                raise _fail(self.file, where, "keypoint (points2D) not finite")
            facts.points2D[image_id] = num_points2D
        self.done()

    def points3D(self, facts: _Facts) -> None:
        seen: set[int] = set()
        tracks = _Tracks()
        for k in self.records():
            point_id, x, y, z, _, _, _, _, track_length = self.take("Q3d3BdQ", f"point record {k}")
            where = f"point {point_id}"
            _check_point(self.file, where, seen, point_id, (x, y, z))
            tracks.add(where, self.array("<u4", 2 * track_length, where))
        self.done()
        tracks.check(self.file, facts)


class _Text:
    """The text files: ``#`` comments, one record per line (two per image), fields
    separated by single spaces (COLMAP's reader splits on ' ')."""

    def __init__(self, file: Path):
        self.file = file
        try:
            self.lines = read_bytes(file).decode("utf-8").splitlines()
        except UnicodeDecodeError:
            raise _fail(file, "text", "not UTF-8 text") from None

    def records(self):
        """(line number, fields) of every record line; images.txt reads its second lines itself."""
        self.position = 0
        while self.position < len(self.lines):
            self.position += 1
            line = self.lines[self.position - 1].strip()
            if line and not line.startswith("#"):
                yield self.position, self.split(line, self.position)

    def split(self, line: str, number: int) -> list[str]:
        fields = line.split(" ")
        if "" in fields:
            raise _fail(self.file, f"line {number}", "two spaces in a row (fields are separated by one space)")
        return fields

    def numbers(self, tokens: list[str], kind, where: str) -> list:
        try:
            return [kind(token) for token in tokens]
        except ValueError:
            bad = next(t for t in tokens if not _parses(kind, t))
            raise _fail(self.file, where, f"{bad[:30]!r} is not {'an integer' if kind is int else 'a number'}") \
                from None

    def fields(self, tokens: list[str], count: int, where: str) -> None:
        if len(tokens) < count:
            raise _fail(self.file, where, f"{len(tokens)} fields, expected at least {count}")

    def cameras(self, facts: _Facts) -> None:
        models = {name: (model, entry) for model, (name, *entry) in colmap_camera_models().items()}
        for number, tokens in self.records():
            where = f"line {number}"
            self.fields(tokens, 4, where)
            camera_id, width, height = self.numbers([tokens[0], tokens[2], tokens[3]], int, where)
            if tokens[1] not in models:
                raise _fail(self.file, where, f"unknown camera model {tokens[1][:30]!r}")
            model, (num_params, *_) = models[tokens[1]]
            params = self.numbers(tokens[4:], float, where)
            if len(params) != num_params:
                raise _fail(self.file, where, f"{tokens[1]} needs {num_params} params, got {len(params)}")
            _check_camera_values(self.file, where, model, width, height, params)
            facts.cameras.add(camera_id)

    def rigs(self, facts: _Facts) -> None:
        facts.framed_images = facts.framed_images or set()
        for number, tokens in self.records():
            where = f"line {number}"
            self.fields(tokens, 2, where)
            rig_id, num_sensors = self.numbers(tokens[:2], int, where)
            rest = tokens[2:]
            for k in range(num_sensors):
                self.fields(rest, 2 if k == 0 else 3, where)
                self.sensor(facts, where, rest[0], self.numbers(rest[1:2], int, where)[0])
                if k == 0:
                    rest = rest[2:]
                elif rest[2] == "1":
                    self.fields(rest, 10, where)
                    _check_pose(self.file, where, self.numbers(rest[3:10], float, where), "sensor_from_rig")
                    rest = rest[10:]
                else:
                    rest = rest[3:]
            facts.rigs.add(rig_id)

    def sensor(self, facts: _Facts, where: str, sensor_type: str, sensor_id: int) -> None:
        if sensor_type not in ("CAMERA", "IMU"):
            raise _fail(self.file, where, f"unknown sensor type {sensor_type[:30]!r}")
        if sensor_type == "CAMERA" and sensor_id not in facts.cameras:
            raise _fail(self.file, where, f"camera {sensor_id} is not in the cameras file")

    def frames(self, facts: _Facts) -> None:
        framed = facts.framed_images = facts.framed_images or set()
        for number, tokens in self.records():
            where = f"line {number}"
            self.fields(tokens, 10, where)
            frame_id, rig_id = self.numbers(tokens[:2], int, where)
            if rig_id not in facts.rigs:
                raise _fail(self.file, where, f"rig {rig_id} is not in the rigs file")
            _check_pose(self.file, where, self.numbers(tokens[2:9], float, where), "rig_from_world")
            (num_data,) = self.numbers(tokens[9:10], int, where)
            self.fields(tokens, 10 + 3 * num_data, where)
            for k in range(num_data):
                sensor_type, sensor_id, data_id = tokens[10 + 3 * k: 13 + 3 * k]
                self.numbers([sensor_id, data_id], int, where)
                if sensor_type == "CAMERA":
                    framed.add(int(data_id))

    def images(self, facts: _Facts) -> None:
        for number, tokens in self.records():
            where = f"line {number}"
            self.fields(tokens, 10, where)
            image_id, camera_id = self.numbers([tokens[0], tokens[8]], int, where)
            _check_pose(self.file, where, self.numbers(tokens[1:8], float, where))
            _check_image(self.file, where, facts, image_id, camera_id)
            _check_name(self.file, where, tokens[9].encode())
            self.position += 1  # the keypoint line follows directly, even when empty
            points_line = self.lines[self.position - 1].strip() if self.position <= len(self.lines) else ""
            points = self.split(points_line, self.position) if points_line else []
            if len(points) % 3:
                raise _fail(self.file, f"line {self.position}", f"{len(points)} fields, expected X Y POINT3D_ID "
                                                                "triples")
            xy = np.array(self.numbers([p for k, p in enumerate(points) if k % 3 != 2], float,
                                       f"line {self.position}"))
            self.numbers(points[2::3], int, f"line {self.position}")
            if not np.all(np.isfinite(xy)):
                raise _fail(self.file, f"line {self.position}", "keypoint (points2D) not finite")
            facts.points2D[image_id] = len(points) // 3

    def points3D(self, facts: _Facts) -> None:
        seen: set[int] = set()
        tracks = _Tracks()
        for number, tokens in self.records():
            where = f"line {number}"
            self.fields(tokens, 8, where)
            point_id, *_ = self.numbers([tokens[0], *tokens[4:7]], int, where)
            xyz = self.numbers(tokens[1:4], float, where)
            self.numbers(tokens[7:8], float, where)
            _check_point(self.file, where, seen, point_id, xyz)
            if len(tokens) % 2:
                raise _fail(self.file, where, "a track element without its POINT2D_IDX")
            tracks.add(where, self.numbers(tokens[8:], int, where))
        tracks.check(self.file, facts)


def _parses(kind, token: str) -> bool:
    try:
        kind(token)
        return True
    except ValueError:
        return False


def _check_image(file: Path, where: str, facts: _Facts, image_id: int, camera_id: int) -> None:
    if camera_id not in facts.cameras:
        raise _fail(file, where, f"camera {camera_id} is not in the cameras file")
    if facts.framed_images is not None and image_id not in facts.framed_images:
        raise _fail(file, where, "in no frame of the frames file")
    if image_id in facts.points2D:
        raise _fail(file, where, "image id appears twice")


def _check_name(file: Path, where: str, name: bytes) -> None:
    try:
        name.decode("utf-8")
    except UnicodeDecodeError:
        raise _fail(file, where, "name is not UTF-8") from None


def _check_point(file: Path, where: str, seen: set[int], point_id: int, xyz) -> None:
    if point_id in seen or point_id == _INVALID_POINT3D:
        raise _fail(file, where, "point id appears twice" if point_id in seen else "invalid point id")
    seen.add(point_id)
    if not np.all(np.isfinite(xyz)):
        raise _fail(file, where, f"position ({', '.join(map(str, xyz))}): not finite")


class _Tracks:
    """Track elements of every point, checked at once against the images' keypoint counts."""

    def __init__(self):
        self.where: list[str] = []
        self.elements: list = []

    def add(self, where: str, flat) -> None:
        self.where.append(where)
        self.elements.append(np.asarray(flat, dtype=np.int64).reshape(-1, 2))

    def check(self, file: Path, facts: _Facts) -> None:
        if not self.elements:
            return
        elements = np.concatenate(self.elements)
        owner = np.repeat(np.arange(len(self.elements)), [len(e) for e in self.elements])
        image_ids = np.array(sorted(facts.points2D), dtype=np.int64)
        counts = np.array([facts.points2D[i] for i in image_ids.tolist()], dtype=np.int64)
        row = np.minimum(np.searchsorted(image_ids, elements[:, 0]), max(len(image_ids) - 1, 0))
        known = (image_ids[row] == elements[:, 0]) if len(image_ids) else np.zeros(len(elements), bool)
        bad = ~known | (elements[:, 1] < 0) | (elements[:, 1] >= np.where(known, counts[row] if len(counts) else 0, 0))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            image_id, index = (int(v) for v in elements[k])
            where = self.where[owner[k]]
            if not known[k]:
                raise _fail(file, where, f"track element of image {image_id}, not in the images file")
            raise _fail(file, where, f"track element: keypoint {index} of image {image_id}, which has "
                                     f"{facts.points2D[image_id]}")
