"""The bad-input corpus of issue 21, built from the bundled fixtures (tests/test_bad_inputs.py
runs it): every kind of broken input, destination and workspace rotonly must answer with one
line naming the file and the field, exit 2 (bad input or usage), nothing written, inputs
byte-identical, no traceback.

A case is a name, a builder and what the error line must hold. The builder makes the case's
files in its folder ``root`` (copies of the fixtures, then broken) and returns the command
line; ``bases`` holds what several cases share (a COLMAP model and a workspace written by
one `rotonly run` of the 4-image fixture). OUT is always ``root/new1/new2/OUT``: a case that
leaves ``new1`` behind made folders for a bad input.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import struct
import zipfile
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from helpers import DATA_FIXTURES

HJ = DATA_FIXTURES / "herzjesu_p8"
HJ_DB = HJ / "database.db"  # pycolmap 4.2 schema, 8 images, stored relative poses
HJ4_DB = DATA_FIXTURES / "colmap38_herzjesu4" / "database.db"  # COLMAP 3.8 schema, 4 images
ESTIMATE = DATA_FIXTURES / "evalquality" / "Herz-Jesus-P8-perturbed" / "sfm_data.json"
OUT = ("new1", "new2", "OUT")
DEEP = "[" * 100_000 + "]" * 100_000
HUGE = "9" * 5000


@dataclass(frozen=True)
class Case:
    name: str
    build: Callable[[Path, dict], list]
    expect: tuple[str, ...]  # substrings of the error line: the file and the field
    code: int = 2


def out(root: Path) -> Path:
    return root.joinpath(*OUT)


# ============================================================================ COLMAP databases

def _db(root: Path, base: Path = HJ_DB, name: str = "database.db") -> Path:
    path = root / name
    shutil.copyfile(base, path)
    return path


def _edit_db(path: Path, *statements) -> None:
    """Each statement: SQL text, (SQL, parameters) or a callable(connection)."""
    with closing(sqlite3.connect(path)) as connection:
        for statement in statements:
            if callable(statement):
                statement(connection)
            elif isinstance(statement, tuple):
                connection.execute(*statement)
            else:
                connection.executescript(statement)
        connection.commit()


def db_case(name: str, expect: tuple[str, ...], *statements, base: Path = HJ_DB, command: str = "run") -> Case:
    def build(root: Path, bases: dict) -> list:
        path = _db(root, base)
        _edit_db(path, *statements)
        if command == "convert":
            return ["convert", path, "-o", out(root).with_suffix(".json")]
        return [command, path, "-o", out(root)]

    return Case(name, build, ("database.db", *expect))


def _blob(table: str, column: str, key: str, key_value: int, change: Callable[[bytes], bytes]):
    def edit(connection):
        (blob,) = connection.execute(f"SELECT {column} FROM {table} WHERE {key} = ?", (key_value,)).fetchone()
        connection.execute(f"UPDATE {table} SET {column} = ? WHERE {key} = ?", (change(blob), key_value))
    return edit


def _floats(dtype: str, index: int, value: float) -> Callable[[bytes], bytes]:
    def change(blob: bytes) -> bytes:
        values = np.frombuffer(blob, dtype=dtype).copy()
        values[index] = value
        return values.tobytes()
    return change


PAIR_12 = 2147483647 * 1 + 2  # pair_id of images (1, 2)


def _params(*values: float) -> tuple:
    return ("UPDATE cameras SET params = ?", (np.array(values, dtype="<f8").tobytes(),))


DB_CASES = [
    db_case("db-keypoints-truncated-blob", ("keypoints of image 3", "blob of 10180 bytes, expected 25896"),
            "UPDATE keypoints SET data = substr(data, 1, 10180) WHERE image_id = 3"),
    db_case("db-keypoints-rows-too-large", ("keypoints of image 2", "expected"),
            "UPDATE keypoints SET rows = rows + 1 WHERE image_id = 2"),
    db_case("db-keypoints-three-cols", ("keypoints of image 1", "cols 3"),
            "UPDATE keypoints SET cols = 3 WHERE image_id = 1"),
    db_case("db-keypoints-negative-rows", ("keypoints of image 1", "rows -5"),
            "UPDATE keypoints SET rows = -5 WHERE image_id = 1"),
    db_case("db-keypoints-text-data", ("keypoints of image 4", "data is text"),
            "UPDATE keypoints SET data = 'abc' WHERE image_id = 4"),
    db_case("db-keypoints-null-data", ("keypoints of image 4", "data is null"),
            "UPDATE keypoints SET data = NULL WHERE image_id = 4"),
    db_case("db-keypoint-nan", ("keypoints of image 2", "not finite"),
            _blob("keypoints", "data", "image_id", 2, _floats("<f4", 7, np.nan))),
    db_case("db-keypoint-inf", ("keypoints of image 5", "not finite"),
            _blob("keypoints", "data", "image_id", 5, _floats("<f4", 0, np.inf))),
    db_case("db-matches-truncated", ("matches of pair (1, 2)", "blob of"),
            ("UPDATE matches SET data = substr(data, 1, 100) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-matches-three-cols", ("matches of pair (1, 2)", "cols 3"),
            ("UPDATE matches SET cols = 3 WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-matches-missing-image", ("matches: pair_id", "image 99"),
            ("UPDATE matches SET pair_id = ? WHERE pair_id = ?", (2147483647 * 1 + 99, PAIR_12))),
    db_case("db-matches-pair-reversed", ("matches: pair_id", "smaller id must come first"),
            ("UPDATE matches SET pair_id = ? WHERE pair_id = ?", (2147483647 * 9 + 1, PAIR_12))),
    db_case("db-matches-negative-pair-id", ("matches: pair_id -1",),
            ("UPDATE matches SET pair_id = -1 WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-blob-truncated", ("two_view_geometries of pair (1, 2)", "blob of"),
            ("UPDATE two_view_geometries SET data = substr(data, 1, 10) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-rows-zero-with-data", ("two_view_geometries of pair (1, 2)", "expected 0"),
            ("UPDATE two_view_geometries SET rows = 0 WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-config-unknown", ("two_view_geometries of pair (1, 2)", "config 42"),
            ("UPDATE two_view_geometries SET config = 42 WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-config-text", ("two_view_geometries of pair (1, 2)", "config"),
            ("UPDATE two_view_geometries SET config = 'CALIBRATED' WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-F-short", ("two_view_geometries of pair (1, 2)", "F: 10 bytes"),
            ("UPDATE two_view_geometries SET F = zeroblob(10) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-E-text", ("two_view_geometries of pair (1, 2)", "E:"),
            ("UPDATE two_view_geometries SET E = 'essential' WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-qvec-short", ("two_view_geometries of pair (1, 2)", "qvec: 8 bytes"),
            ("UPDATE two_view_geometries SET qvec = zeroblob(8) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-tvec-short", ("two_view_geometries of pair (1, 2)", "tvec: 16 bytes"),
            ("UPDATE two_view_geometries SET tvec = zeroblob(16) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-qvec-nan", ("two_view_geometries of pair (1, 2)", "qvec", "not finite"),
            _blob("two_view_geometries", "qvec", "pair_id", PAIR_12, _floats("<f8", 1, np.nan))),
    db_case("db-geometry-tvec-inf", ("two_view_geometries of pair (1, 2)", "tvec", "not finite"),
            _blob("two_view_geometries", "tvec", "pair_id", PAIR_12, _floats("<f8", 2, -np.inf))),
    db_case("db-geometry-qvec-without-tvec", ("two_view_geometries of pair (1, 2)", "one is set"),
            ("UPDATE two_view_geometries SET tvec = NULL WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-camera1-garbage", ("two_view_geometries of pair (1, 2): camera1",),
            ("UPDATE two_view_geometries SET camera1 = zeroblob(12) WHERE pair_id = ?", (PAIR_12,))),
    db_case("db-geometry-camera2-bad-model", ("two_view_geometries of pair (1, 2): camera2", "camera model 77"),
            ("UPDATE two_view_geometries SET camera2 = ? WHERE pair_id = ?",
             (struct.pack("<IiQQBQ", 1, 77, 100, 100, 0, 1) + b"\0" * 8, PAIR_12))),
    db_case("db-camera-model-unknown", ("cameras: camera 1", "unknown camera model id 99"),
            "UPDATE cameras SET model = 99"),
    db_case("db-camera-model-invalid", ("cameras: camera 1", "unknown camera model id -1"),
            "UPDATE cameras SET model = -1"),
    db_case("db-camera-params-count", ("cameras: camera 1", "params blob of 24 bytes, expected 32"),
            _params(1380.0, 768.0, 512.0)),
    db_case("db-camera-params-count-for-model", ("cameras: camera 1", "params blob of 32 bytes, expected 24"),
            "UPDATE cameras SET model = 0"),
    db_case("db-camera-params-null", ("cameras: camera 1", "no params blob"),
            "UPDATE cameras SET params = NULL"),
    db_case("db-camera-focal-nan", ("cameras: camera 1", "parameter 0 is nan"), _params(np.nan, 1380, 768, 512)),
    db_case("db-camera-focal-inf", ("cameras: camera 1", "parameter 1 is inf"), _params(1380, np.inf, 768, 512)),
    db_case("db-camera-focal-negative", ("cameras: camera 1", "focal length -1380.0"),
            _params(-1380.0, 1380, 768.0, 512.0)),
    db_case("db-camera-focal-zero", ("cameras: camera 1", "focal length 0.0"), _params(1380, 0.0, 768.0, 512.0)),
    db_case("db-camera-principal-point-outside", ("cameras: camera 1", "principal point (9000.0, 512.0)"),
            _params(1380, 1380, 9000.0, 512.0)),
    db_case("db-camera-principal-point-negative", ("cameras: camera 1", "principal point (768.0, -3.0)"),
            _params(1380, 1380, 768.0, -3.0)),
    db_case("db-camera-principal-point-nan", ("cameras: camera 1", "parameter 3 is nan"),
            _params(1380, 1380, 768.0, np.nan)),
    db_case("db-camera-distortion-nan", ("cameras: camera 1", "parameter 3 is nan"),
            "UPDATE cameras SET model = 2", _params(1380.0, 768.0, 512.0, np.nan)),
    db_case("db-camera-distortion-inf-radial", ("cameras: camera 1", "parameter 4 is -inf"),
            "UPDATE cameras SET model = 3", _params(1380.0, 768.0, 512.0, 0.01, -np.inf)),
    db_case("db-camera-width-zero", ("cameras: camera 1", "width 0"), "UPDATE cameras SET width = 0"),
    db_case("db-camera-height-negative", ("cameras: camera 1", "height -5"), "UPDATE cameras SET height = -5"),
    db_case("db-camera-width-text", ("cameras: camera 1", "width"), "UPDATE cameras SET width = 'wide'"),
    db_case("db-image-missing-camera", ("images: image 2", "camera 7"),
            "UPDATE images SET camera_id = 7 WHERE image_id = 2"),
    db_case("db-image-name-not-utf8", ("images: image 3", "not UTF-8"),
            ("UPDATE images SET name = CAST(? AS TEXT) WHERE image_id = 3", (b"\xff\xfe.jpg",))),
    db_case("db-image-name-blob", ("images: image 3", "expected text"),
            ("UPDATE images SET name = ? WHERE image_id = 3", (b"0003.jpg",))),
    db_case("db-table-keypoints-missing", ("keypoints", "without this table"), "DROP TABLE keypoints"),
    db_case("db-table-cameras-missing", ("cameras", "without this table"), "DROP TABLE cameras"),
    db_case("db-table-geometries-missing", ("two_view_geometries", "without this table"),
            "DROP TABLE two_view_geometries"),
    db_case("db38-keypoints-truncated", ("keypoints of image 2", "blob of 100 bytes"),
            "UPDATE keypoints SET data = substr(data, 1, 100) WHERE image_id = 2", base=HJ4_DB),
    db_case("db38-focal-nan", ("cameras: camera 1", "not finite"), _params(np.nan, 1380, 768.0, 512.0),
            base=HJ4_DB),
    db_case("db38-focal-negative", ("cameras: camera 1", "focal length -5.0"), _params(1380, -5.0, 768.0, 512.0),
            base=HJ4_DB),
    db_case("db38-qvec-nan", ("two_view_geometries of pair (1, 2)", "qvec"),
            _blob("two_view_geometries", "qvec", "pair_id", PAIR_12, _floats("<f8", 0, np.nan)), base=HJ4_DB),
    db_case("db38-F-short", ("two_view_geometries of pair (1, 2)", "F: 8 bytes"),
            ("UPDATE two_view_geometries SET F = zeroblob(8) WHERE pair_id = ?", (PAIR_12,)), base=HJ4_DB),
    db_case("db-identify-keypoints-truncated", ("keypoints of image 3",),
            "UPDATE keypoints SET data = substr(data, 1, 64) WHERE image_id = 3", command="identify"),
    db_case("db-convert-camera-model-unknown", ("cameras: camera 1", "unknown camera model id"),
            "UPDATE cameras SET model = 1000", command="convert"),
]


def _raw_file_case(name: str, content: bytes, expect: tuple[str, ...], file: str = "database.db") -> Case:
    def build(root: Path, bases: dict) -> list:
        (root / file).write_bytes(content)
        return ["run", root / file, "-o", out(root)]

    return Case(name, build, (file, *expect))


def _truncated_db(root: Path, bases: dict) -> list:
    path = root / "database.db"
    path.write_bytes(HJ_DB.read_bytes()[:8192])
    return ["run", path, "-o", out(root)]


def _folder_with_sfm_data_bin(root: Path, bases: dict) -> list:
    (root / "project").mkdir()
    (root / "project" / "sfm_data.bin").write_bytes(b"\x02\x00\x00\x00cereal")
    return ["run", root / "project", "-o", out(root)]


def _matches_file_of_project(root: Path, bases: dict) -> list:
    """An OpenMVG project's matches file given as the input, beside its sfm_data.json."""
    (root / "sfm_data.json").write_text("{}")
    (root / "matches.putative.bin").write_bytes(b"\x01\x00\x00\x00cereal")
    return ["run", root / "matches.putative.bin", "-o", out(root)]


def _sqlite_without_tables(root: Path, bases: dict) -> list:
    path = root / "database.db"
    with closing(sqlite3.connect(path)) as connection:
        connection.execute("CREATE TABLE things (x)")
        connection.commit()
    return ["run", path, "-o", out(root)]


FILE_CASES = [
    _raw_file_case("db-empty-file", b"", ("not an SQLite file",)),
    _raw_file_case("db-random-bytes", bytes(range(256)) * 10, ("not an SQLite file",)),
    _raw_file_case("db-sqlite-magic-only", b"SQLite format 3\x00" + b"\0" * 100, ("SQLite",)),
    _raw_file_case("input-unknown-extension", b"hello", ("not an SQLite file",), file="input.txt"),
    Case("db-truncated-sqlite", _truncated_db, ("database.db",)),
    Case("db-sqlite-without-colmap-tables", _sqlite_without_tables, ("database.db", "cameras", "without this table")),
    Case("input-missing", lambda root, bases: ["run", root / "missing.db", "-o", out(root)],
         ("missing.db", "no such file")),
    Case("input-folder-without-project", lambda root, bases: ["run", root, "-o", out(root)],
         (str(os.sep), "neither a COLMAP model")),
    # the formats rotonly does not read, named with what to do: OpenMVG's other sfm_data
    # serializations (its converter writes the .json) and one file of a COLMAP model
    _raw_file_case("input-openmvg-sfm-data-bin", b"\x02\x00\x00\x00cereal", (
        "OpenMVG sfm_data in binary form", "openMVG_main_ConvertSfM_DataFormat -i"), file="sfm_data.bin"),
    _raw_file_case("input-openmvg-sfm-data-xml", b"<?xml version=\"1.0\"?><cereal/>", (
        "in XML form", "sfm_data.json"), file="sfm_data.xml"),
    Case("input-folder-with-openmvg-sfm-data-bin", _folder_with_sfm_data_bin,
         ("neither a COLMAP model", "sfm_data.bin looks like an OpenMVG sfm_data",
          "openMVG_main_ConvertSfM_DataFormat")),
    _raw_file_case("input-colmap-model-file", b"\x00" * 8, ("a COLMAP model is read from its folder",),
                   file="images.bin"),
    Case("input-openmvg-matches-file", _matches_file_of_project,
         ("matches.putative.bin looks like an OpenMVG matches file", "-M", "sfm_data.json -M")),
]


# ============================================================================ special files

def _fifo(name: str, command: str = "run") -> Callable:
    def build(root: Path, bases: dict) -> list:
        os.mkfifo(root / name)
        if command == "eval":
            return ["eval", "--gt", root / name, ESTIMATE, "-o", out(root)]
        if command == "gt":
            return ["run", HJ_DB, "-o", out(root), "--gt", root / name]
        return ["run", root / name, "-o", out(root)]
    return build


def _project_with_fifo(name: str) -> Callable:
    def build(root: Path, bases: dict) -> list:
        project = _project(root)
        (project / name).unlink()
        os.mkfifo(project / name)
        return ["run", project / "sfm_data.json", "-o", out(root)]
    return build


def _device(name: str, device: str = "/dev/null", command: str = "run") -> Callable:
    def build(root: Path, bases: dict) -> list:
        os.symlink(device, root / name)  # stat follows it: a character device
        if command == "eval":
            return ["eval", "--gt", HJ, root / name, "-o", out(root)]
        return ["run", root / name, "-o", out(root)]
    return build


SPECIAL_CASES = [
    Case("fifo-database", _fifo("database.db"), ("database.db", "named pipe")),
    Case("fifo-sfm-data", _fifo("sfm_data.json"), ("sfm_data.json", "named pipe")),
    Case("fifo-gt-json", _fifo("gt.json", "gt"), ("gt.json", "--gt", "named pipe")),
    Case("fifo-eval-gt", _fifo("gt.json", "eval"), ("gt.json", "--gt", "named pipe")),
    Case("fifo-feat", _project_with_fifo("0003.feat"), ("0003.feat", "named pipe")),
    Case("fifo-matches", _project_with_fifo("matches.e.bin"), ("matches.e.bin", "named pipe")),
    Case("device-database", _device("database.db"), ("database.db", "character device")),
    Case("device-sfm-data", _device("sfm_data.json", "/dev/zero"), ("sfm_data.json", "character device")),
    Case("device-eval-estimate", _device("estimate.json", "/dev/zero", "eval"),
         ("estimate.json", "ESTIMATE", "character device")),
]


# ============================================================================ OpenMVG projects

def _project(root: Path) -> Path:
    project = root / "project"
    shutil.copytree(HJ / "openmvg", project)
    return project


def intrinsic(doc: dict) -> dict:
    return doc["intrinsics"][0]["value"]["ptr_wrapper"]["data"]


def view(doc: dict, k: int = 0) -> dict:
    return doc["views"][k]["value"]["ptr_wrapper"]["data"]


def _setter(getter: Callable, key: str, value) -> Callable:
    def mutate(doc: dict) -> None:
        getter(doc)[key] = value
    return mutate


SENTINEL = 271828.125  # a number the raw-text edits replace


def mvg_case(name: str, expect: tuple[str, ...], mutate: Callable | None = None,
             raw: Callable[[str], str] | None = None, files: dict | None = None, command: str = "run") -> Case:
    """An OpenMVG project copy whose sfm_data.json is edited (``mutate`` on the document,
    ``raw`` on its text) and whose other ``files`` (name -> bytes) are replaced."""
    def build(root: Path, bases: dict) -> list:
        project = _project(root)
        document = json.loads((project / "sfm_data.json").read_text())
        if mutate is not None:
            mutate(document)
        text = json.dumps(document, indent=1)
        (project / "sfm_data.json").write_text(raw(text) if raw else text)
        for file, content in (files or {}).items():
            (project / file).write_bytes(content)
        if command == "eval":
            return ["eval", "--gt", HJ, project / "sfm_data.json", "-o", out(root)]
        if command == "convert":
            return ["convert", project / "sfm_data.json", "-o", out(root).with_suffix(".db")]
        return [command, project / "sfm_data.json", "-o", out(root)]

    return Case(name, build, expect)


def _raw(old: str, new: str) -> Callable[[str], str]:
    return lambda text: text.replace(old, new)


def _sentinel_focal(doc: dict) -> None:
    intrinsic(doc)["focal_length"] = SENTINEL


def _feat_lines(change: Callable[[list[str]], list[str]], stem: str = "0002") -> dict:
    lines = (HJ / "openmvg" / f"{stem}.feat").read_text().splitlines()
    return {f"{stem}.feat": ("\n".join(change(lines)) + "\n").encode()}


def _matches_bin(change: Callable[[bytes], bytes]) -> dict:
    return {"matches.e.bin": change((HJ / "openmvg" / "matches.e.bin").read_bytes())}


def _first_pair(payload: bytes, i: int, j: int, first_match: tuple[int, int] | None = None) -> bytes:
    """matches.e.bin with the first pair's view ids (and first match) replaced."""
    data = bytearray(payload)
    struct.pack_into("<II", data, 9, i, j)
    if first_match is not None:
        struct.pack_into("<II", data, 9 + 16, *first_match)
    return bytes(data)


MVG = "sfm_data.json"
FOCAL = "intrinsics[key=0].ptr_wrapper.data.focal_length"
MVG_CASES = [
    mvg_case("json-deep-nesting", (MVG, "nested 100000 levels"), raw=lambda text: DEEP),
    mvg_case("json-deep-nesting-inside", (MVG, "nested"),
             raw=lambda text: text.replace('"control_points": []', '"control_points": ' + DEEP)),
    mvg_case("json-huge-integer-id", (MVG, "id_view", "5000 characters"),
             raw=lambda text: text.replace('"id_view": 0', f'"id_view": {HUGE}', 1)),
    mvg_case("json-huge-integer-focal", (MVG, FOCAL, "5000 characters"), _sentinel_focal,
             raw=_raw(str(SENTINEL), HUGE)),
    mvg_case("json-focal-1e400", (MVG, FOCAL, "not a finite number"), _sentinel_focal,
             raw=_raw(str(SENTINEL), "1e400")),
    mvg_case("json-focal-NaN", (MVG, FOCAL, "not a finite number"), _sentinel_focal, raw=_raw(str(SENTINEL), "NaN")),
    mvg_case("json-focal-Infinity", (MVG, FOCAL, "not a finite number"), _sentinel_focal,
             raw=_raw(str(SENTINEL), "-Infinity")),
    mvg_case("json-focal-negative", (MVG, "intrinsics[key=0]", "focal length -1380.91"),
             _setter(intrinsic, "focal_length", -1380.91)),
    mvg_case("json-focal-zero", (MVG, "intrinsics[key=0]", "focal length 0.0"),
             _setter(intrinsic, "focal_length", 0)),
    mvg_case("json-focal-string", (MVG, FOCAL, "expected a number"), _setter(intrinsic, "focal_length", "1380")),
    mvg_case("json-focal-null", (MVG, FOCAL, "expected a number"), _setter(intrinsic, "focal_length", None)),
    mvg_case("json-focal-bool", (MVG, FOCAL, "expected a number"), _setter(intrinsic, "focal_length", True)),
    mvg_case("json-focal-missing", (MVG, FOCAL, "missing field"),
             lambda doc: intrinsic(doc).pop("focal_length")),
    mvg_case("json-principal-point-outside", (MVG, "intrinsics[key=0]", "principal point"),
             _setter(intrinsic, "principal_point", [5000.0, 503.0])),
    mvg_case("json-principal-point-negative", (MVG, "intrinsics[key=0]", "principal point"),
             _setter(intrinsic, "principal_point", [760.0, -40.0])),
    mvg_case("json-principal-point-nan", (MVG, "principal_point[1]", "not a finite number"),
             _setter(intrinsic, "principal_point", [760.0, SENTINEL]), raw=_raw(str(SENTINEL), "NaN")),
    mvg_case("json-principal-point-one-value", (MVG, "principal_point", "expected 2 numbers"),
             _setter(intrinsic, "principal_point", [760.0])),
    mvg_case("json-intrinsic-width-zero", (MVG, "intrinsics[key=0]", "width 0"), _setter(intrinsic, "width", 0)),
    mvg_case("json-intrinsic-height-negative", (MVG, "intrinsics[key=0].ptr_wrapper.data.height", "-1024"),
             _setter(intrinsic, "height", -1024)),
    mvg_case("json-intrinsic-width-float", (MVG, "intrinsics[key=0].ptr_wrapper.data.width", "1536.0"),
             _setter(intrinsic, "width", 1536.0)),
    mvg_case("json-intrinsic-unknown-type", (MVG, "polymorphic_name", "unsupported intrinsic type"),
             lambda doc: doc["intrinsics"][0]["value"].update(polymorphic_name="pinhole_magic")),
    mvg_case("json-distortion-nan", (MVG, "disto_k3[1]", "not a finite number"),
             lambda doc: doc["intrinsics"][0]["value"].update(polymorphic_name="pinhole_radial_k3")
             or intrinsic(doc).update(disto_k3=[0.0, SENTINEL, 0.0]), raw=_raw(str(SENTINEL), "NaN")),
    mvg_case("json-distortion-short", (MVG, "disto_k3", "expected 3 numbers"),
             lambda doc: doc["intrinsics"][0]["value"].update(polymorphic_name="pinhole_radial_k3")
             or intrinsic(doc).update(disto_k3=[0.0, 0.0])),
    mvg_case("json-view-width-zero", (MVG, "views[key=0].ptr_wrapper.data.width", "must be > 0"),
             _setter(view, "width", 0)),
    mvg_case("json-view-id-mismatch", (MVG, "id_view", "differs from the map key"), _setter(view, "id_view", 5)),
    mvg_case("json-view-duplicate-key", (MVG, "views[1].key", "duplicate key 0"),
             lambda doc: doc["views"][1].update(key=0)),
    mvg_case("json-view-filename-number", (MVG, "filename", "expected a string"), _setter(view, "filename", 7)),
    mvg_case("json-polymorphic-id-dangling", (MVG, "polymorphic_id", "refers to no earlier"),
             lambda doc: doc["intrinsics"][0]["value"].update(polymorphic_id=5)),
    mvg_case("json-ptr-id-dangling", (MVG, "ptr_wrapper.id", "refers to no earlier object"),
             lambda doc: doc["views"][0]["value"]["ptr_wrapper"].update(id=3)),
    mvg_case("json-views-missing", (MVG, "views", "missing field"), lambda doc: doc.pop("views")),
    mvg_case("json-views-object", (MVG, "views", "expected an array"), lambda doc: doc.update(views={})),
    mvg_case("json-top-level-array", (MVG, "top level"), raw=lambda text: "[1, 2, 3]"),
    mvg_case("json-truncated", (MVG, "malformed JSON"), raw=lambda text: text[: len(text) // 2]),
    mvg_case("json-not-utf8", (MVG, "malformed JSON"), files={MVG: b'{"sfm_data_version": "\xff\xfe"}'}),
    mvg_case("json-empty", (MVG, "malformed JSON"), raw=lambda text: ""),
    mvg_case("json-version-number", (MVG, "sfm_data_version", "expected a string"),
             lambda doc: doc.update(sfm_data_version=0.3)),
    mvg_case("feat-nan", ("0002.feat", "line 3", "non-finite"), files=_feat_lines(
        lambda lines: lines[:2] + ["nan 1 1 0"] + lines[3:])),
    mvg_case("feat-inf", ("0002.feat", "line 1", "non-finite"), files=_feat_lines(
        lambda lines: ["10 inf 1 0"] + lines[1:])),
    mvg_case("feat-three-columns", ("0002.feat", "line 5", "3 columns"), files=_feat_lines(
        lambda lines: lines[:4] + ["1 2 3"] + lines[5:])),
    mvg_case("feat-text", ("0002.feat", "line 2", "non-numeric"), files=_feat_lines(
        lambda lines: lines[:1] + ["a b c d"] + lines[2:])),
    mvg_case("feat-binary-garbage", ("0002.feat",), files={"0002.feat": bytes(range(256))}),
    Case("feat-missing", lambda root, bases: _remove_and_run(root, "0005.feat"), ("0005.feat", "file not found")),
    mvg_case("feat-too-few-for-matches", ("matches.e.bin", "keypoints of view"), files=_feat_lines(
        lambda lines: lines[:10])),
    mvg_case("matches-truncated-header", ("matches.e.bin", "header", "truncated"),
             files=_matches_bin(lambda data: data[:5])),
    mvg_case("matches-truncated-pair", ("matches.e.bin", "truncated"), files=_matches_bin(lambda data: data[:-12])),
    mvg_case("matches-trailing-bytes", ("matches.e.bin", "trailer", "unexpected bytes"),
             files=_matches_bin(lambda data: data + b"\0" * 5)),
    mvg_case("matches-endianness-flag", ("matches.e.bin", "header", "endianness"),
             files=_matches_bin(lambda data: b"\x07" + data[1:])),
    mvg_case("matches-huge-pair-count", ("matches.e.bin", "truncated"),
             files=_matches_bin(lambda data: data[:1] + struct.pack("<Q", 2 ** 62) + data[9:])),
    mvg_case("matches-unknown-view", ("matches.e.bin", "view 41 is not in sfm_data"),
             files=_matches_bin(lambda data: _first_pair(data, 0, 41))),
    mvg_case("matches-view-with-itself", ("matches.e.bin", "matches a view with itself"),
             files=_matches_bin(lambda data: _first_pair(data, 3, 3))),
    mvg_case("matches-index-out-of-range", ("matches.e.bin", "feature index 4000000000"),
             files=_matches_bin(lambda data: _first_pair(data, *struct.unpack_from("<II", data, 9),
                                                         first_match=(4_000_000_000, 0)))),
    Case("matches-text-not-integer", lambda root, bases: _matches_text(root, "0 1\n2\n1 2\nx 4\n"),
         ("matches.e.txt", "non-integer")),
    Case("matches-text-negative", lambda root, bases: _matches_text(root, "0 1\n1\n-1 2\n"),
         ("matches.e.txt", "negative")),
    Case("matches-text-huge-integer", lambda root, bases: _matches_text(root, f"0 1\n1\n{HUGE} 2\n"),
         ("matches.e.txt",)),
    Case("matches-text-truncated", lambda root, bases: _matches_text(root, "0 1\n5\n1 2\n"),
         ("matches.e.txt", "pair 0", "truncated")),
    Case("matches-none", lambda root, bases: _remove_and_run(root, "matches.e.bin"),
         ("--matches-dir", "no matches file")),
    Case("matches-dir-missing", lambda root, bases: _run_project(root, "--matches-dir", root / "nowhere"),
         ("nowhere", "matches directory not found")),
    mvg_case("eval-estimate-deep-json", (MVG, "nested"), raw=lambda text: DEEP, command="eval"),
    mvg_case("eval-estimate-rotation-nan", (MVG, "extrinsics[key=0].rotation[1][1]", "not a finite"),
             lambda doc: _add_pose(doc, [[1, 0, 0], [0, SENTINEL, 0], [0, 0, 1]]), raw=_raw(str(SENTINEL), "NaN"),
             command="eval"),
    mvg_case("eval-estimate-rotation-not-orthonormal", (MVG, "extrinsics[key=0].rotation", "not a rotation"),
             lambda doc: _add_pose(doc, [[2, 0, 0], [0, 1, 0], [0, 0, 1]]), command="eval"),
    mvg_case("eval-estimate-rotation-short", (MVG, "extrinsics[key=0].rotation[2]", "expected 3 numbers"),
             lambda doc: _add_pose(doc, [[1, 0, 0], [0, 1, 0], [0, 0]]), command="eval"),
    mvg_case("eval-estimate-center-inf", (MVG, "extrinsics[key=0].center[0]", "not a finite"),
             lambda doc: _add_pose(doc, None, [SENTINEL, 0, 0]), raw=_raw(str(SENTINEL), "Infinity"),
             command="eval"),
    mvg_case("eval-estimate-structure-nan", (MVG, "structure[key=0].X[2]", "not a finite"),
             lambda doc: _add_structure(doc, [0, 0, SENTINEL]), raw=_raw(str(SENTINEL), "NaN"), command="eval"),
    mvg_case("identify-focal-nan", (MVG, FOCAL), _sentinel_focal, raw=_raw(str(SENTINEL), "NaN"),
             command="identify"),
    mvg_case("convert-deep-json", (MVG, "nested"), raw=lambda text: DEEP, command="convert"),
]


def _run_project(root: Path, *extra) -> list:
    project = _project(root)
    return ["run", project / "sfm_data.json", "-o", out(root), *extra]


def _remove_and_run(root: Path, name: str) -> list:
    project = _project(root)
    (project / name).unlink()
    return ["run", project / "sfm_data.json", "-o", out(root)]


def _matches_text(root: Path, text: str) -> list:
    project = _project(root)
    (project / "matches.e.bin").unlink()
    (project / "matches.e.txt").write_text(text)
    return ["run", project / "sfm_data.json", "-o", out(root)]


def _add_pose(doc: dict, rotation, center=(0.0, 0.0, 0.0)) -> None:
    rotation = rotation if rotation is not None else [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    doc["extrinsics"] = [{"key": 0, "value": {"rotation": rotation, "center": list(center)}}]


def _add_structure(doc: dict, X) -> None:
    _add_pose(doc, None)
    doc["structure"] = [{"key": 0, "value": {"X": X, "observations": [
        {"key": 0, "value": {"id_feat": 0, "x": [1.0, 2.0]}}]}}]


# ============================================================================ Strecha ground truths

def gt_case(name: str, expect: tuple[str, ...], text: Callable[[str], str] | None = None,
            command: str = "run", remove_all: bool = False) -> Case:
    def build(root: Path, bases: dict) -> list:
        gt = root / "gt"
        shutil.copytree(HJ / "gt_dense_cameras", gt / "gt_dense_cameras")
        camera = gt / "gt_dense_cameras" / "0003.jpg.camera"
        if remove_all:
            for file in (gt / "gt_dense_cameras").iterdir():
                file.unlink()
        elif text is not None:
            camera.write_text(text(camera.read_text()))
        if command == "eval":
            return ["eval", "--gt", gt, ESTIMATE, "-o", out(root)]
        return ["run", _db(root), "-o", out(root), "--gt", gt]

    return Case(name, build, expect)


def _last_line(value: str) -> Callable[[str], str]:
    return lambda text: "\n".join(text.strip().splitlines()[:-1] + [value]) + "\n"


def _first_value(value: str) -> Callable[[str], str]:
    return lambda text: value + text.strip()[text.strip().index(" "):] + "\n"


CAMERA = "0003.jpg.camera"
GT_CASES = [
    gt_case("gt-camera-size-nan", (CAMERA, "width height", "whole numbers"), _last_line("nan nan")),
    gt_case("gt-camera-size-nan-eval", (CAMERA, "width height"), _last_line("nan nan"), command="eval"),
    gt_case("gt-camera-size-negative", (CAMERA, "width height"), _last_line("-1536 1024")),
    gt_case("gt-camera-size-fraction", (CAMERA, "width height"), _last_line("1536.5 1024")),
    gt_case("gt-camera-too-few-numbers", (CAMERA, "10 numbers"), lambda text: "1 2 3 4 5 6 7 8 9 10\n"),
    gt_case("gt-camera-not-numbers", (CAMERA, "non-numeric"), lambda text: text.replace("0", "zero", 1)),
    gt_case("gt-camera-K-nan", (CAMERA, "K", "non-finite"), _first_value("nan")),
    gt_case("gt-camera-focal-negative", (CAMERA, "K", "focal length -1379.74"), _first_value("-1379.74")),
    gt_case("gt-camera-focal-zero-eval", (CAMERA, "K", "focal length 0.0"), _first_value("0"), command="eval"),
    gt_case("gt-camera-center-inf", (CAMERA, "C", "non-finite"),
            lambda text: text.replace("-6.71999", "inf") if "-6.71999" in text else _center_inf(text)),
    gt_case("gt-camera-not-ascii", (CAMERA, "not ASCII"), lambda text: "\u00e9" + text),
    gt_case("gt-no-camera-files", ("gt_dense_cameras", "no .camera files"), remove_all=True),
    Case("gt-deep-json", lambda root, bases: _gt_json(root, DEEP), ("gt.json", "nested")),
    Case("gt-huge-number-json", lambda root, bases: _gt_json(root, '{"sfm_data_version": ' + HUGE + '}'),
         ("gt.json", "sfm_data_version", "5000 characters")),
    Case("gt-missing", lambda root, bases: ["run", _db(root), "-o", out(root), "--gt", root / "nothing"],
         ("nothing", "--gt", "no such file")),
    Case("eval-estimate-missing", lambda root, bases: ["eval", "--gt", HJ, root / "none.json", "-o", out(root)],
         ("none.json", "ESTIMATE", "no such file")),
    Case("eval-estimate-not-json", lambda root, bases: _eval_file(root, "estimate.txt", b"1 2 3"),
         ("estimate.txt", "ESTIMATE", "expected an OpenMVG")),
]


def _center_inf(text: str) -> str:
    lines = text.strip().splitlines()
    lines[-2] = "inf 0 0"
    return "\n".join(lines) + "\n"


def _gt_json(root: Path, text: str) -> list:
    (root / "gt.json").write_text(text)
    return ["run", _db(root), "-o", out(root), "--gt", root / "gt.json"]


def _eval_file(root: Path, name: str, content: bytes) -> list:
    (root / name).write_bytes(content)
    return ["eval", "--gt", HJ, root / name, "-o", out(root)]


# ============================================================================ COLMAP models

def model_case(name: str, expect: tuple[str, ...], edit: Callable[[Path], None], text: bool = False,
               command: str = "eval") -> Case:
    def build(root: Path, bases: dict) -> list:
        model = root / "model"
        shutil.copytree(bases["model_txt" if text else "model"], model)
        edit(model)
        if command == "convert":
            return ["convert", model, "-o", out(root).with_suffix(".json")]
        if command == "gt":
            return ["run", _db(root), "-o", out(root), "--gt", model]
        return ["eval", "--gt", HJ, model, "-o", out(root)]

    return Case(name, build, expect)


def _bytes(file: str, change: Callable[[bytearray], bytes | bytearray]) -> Callable[[Path], None]:
    def edit(model: Path) -> None:
        path = model / file
        path.write_bytes(bytes(change(bytearray(path.read_bytes()))))
    return edit


def _pack(layout: str, offset: int, *values) -> Callable[[bytearray], bytearray]:
    def change(data: bytearray) -> bytearray:
        struct.pack_into(layout, data, offset, *values)
        return data
    return change


def _text_line(file: str, line: int, change: Callable[[str], str]) -> Callable[[Path], None]:
    """Edit the ``line``-th record line (0-based, comments skipped) of a text model file."""
    def edit(model: Path) -> None:
        path = model / file
        lines = path.read_text().split("\n")
        records = [k for k, text in enumerate(lines) if text and not text.startswith("#")]
        lines[records[line]] = change(lines[records[line]])
        path.write_text("\n".join(lines))
    return edit


IMAGE_POSE = 8 + 4  # images.bin: count, then the first image's id: its qw is here
MODEL_CASES = [
    model_case("model-cameras-truncated", ("cameras.bin", "camera 1", "truncated"),
               _bytes("cameras.bin", lambda data: data[:40])),
    model_case("model-cameras-unknown-model", ("cameras.bin", "camera 1", "unknown camera model id 55"),
               _bytes("cameras.bin", _pack("<i", 12, 55))),
    model_case("model-cameras-focal-nan", ("cameras.bin", "camera 1", "not finite"),
               _bytes("cameras.bin", _pack("<d", 32, np.nan))),
    model_case("model-cameras-width-zero", ("cameras.bin", "camera 1", "width 0"),
               _bytes("cameras.bin", _pack("<Q", 16, 0))),
    model_case("model-cameras-trailing", ("cameras.bin", "bytes after the last record"),
               _bytes("cameras.bin", lambda data: data + b"\0\0")),
    model_case("model-images-truncated", ("images.bin", "truncated"), _bytes("images.bin", lambda data: data[:-50])),
    model_case("model-images-pose-nan", ("images.bin", "image 1", "not finite"),
               _bytes("images.bin", _pack("<d", IMAGE_POSE, np.nan))),
    model_case("model-images-zero-quaternion", ("images.bin", "image 1", "zero quaternion"),
               _bytes("images.bin", _pack("<4d", IMAGE_POSE, 0.0, 0.0, 0.0, 0.0))),
    model_case("model-images-camera-missing", ("images.bin", "image 1", "camera 9"),
               _bytes("images.bin", _pack("<I", IMAGE_POSE + 56, 9))),
    model_case("model-images-keypoint-nan", ("images.bin", "image 1", "keypoint"),
               _bytes("images.bin", lambda data: _first_keypoint_nan(data))),
    model_case("model-images-count-too-large", ("images.bin", "truncated"),
               _bytes("images.bin", _pack("<Q", 0, 1000))),
    model_case("model-points-truncated", ("points3D.bin", "truncated"),
               _bytes("points3D.bin", lambda data: data[:-3])),
    model_case("model-points-xyz-nan", ("points3D.bin", "point 1", "not finite"),
               _bytes("points3D.bin", _pack("<d", 16, np.nan))),
    model_case("model-points-track-unknown-image", ("points3D.bin", "point 1", "image 77"),
               _bytes("points3D.bin", _pack("<I", 8 + 43 + 8, 77))),
    model_case("model-points-track-keypoint-range", ("points3D.bin", "point 1", "keypoint 9999999"),
               _bytes("points3D.bin", _pack("<I", 8 + 43 + 8 + 4, 9_999_999))),
    model_case("model-frames-unknown-rig", ("frames.bin", "frame 1", "rig 5"),
               _bytes("frames.bin", _pack("<I", 8 + 4, 5))),
    model_case("model-rigs-unknown-camera", ("rigs.bin", "rig 1", "camera 4"),
               _bytes("rigs.bin", _pack("<I", 8 + 8 + 4, 4))),
    model_case("model-frames-missing-image", ("images.bin", "in no frame"),
               _bytes("frames.bin", lambda data: _drop_first_frame_data(data))),
    model_case("model-text-camera-model", ("cameras.txt", "line", "unknown camera model 'PINHOLE_X'"),
               _text_line("cameras.txt", 0, lambda line: line.replace("PINHOLE", "PINHOLE_X")), text=True),
    model_case("model-text-camera-params", ("cameras.txt", "line", "needs 4 params, got 3"),
               _text_line("cameras.txt", 0, lambda line: line.rsplit(" ", 1)[0]), text=True),
    model_case("model-text-camera-focal-negative", ("cameras.txt", "line", "focal length"),
               _text_line("cameras.txt", 0, lambda line: line.replace(" 1379.74", " -1379.74")), text=True),
    model_case("model-text-double-space", ("cameras.txt", "two spaces"),
               _text_line("cameras.txt", 0, lambda line: line.replace(" ", "  ", 1)), text=True),
    model_case("model-text-image-pose-nan", ("images.txt", "line", "not finite"),
               _text_line("images.txt", 0, lambda line: " ".join([line.split(" ")[0], "nan", *line.split(" ")[2:]])),
               text=True),
    model_case("model-text-image-id-text", ("images.txt", "line", "'one' is not an integer"),
               _text_line("images.txt", 0, lambda line: "one" + line[1:]), text=True),
    model_case("model-text-points2d-odd", ("images.txt", "line", "triples"),
               _text_line("images.txt", 1, lambda line: line.rstrip() + " 5"), text=True),
    model_case("model-text-point-track-image", ("points3D.txt", "line", "image 42"),
               _text_line("points3D.txt", 0, lambda line: line + " 42 0"), text=True),
    model_case("model-text-point-xyz-text", ("points3D.txt", "line", "is not a number"),
               _text_line("points3D.txt", 0, lambda line: line.replace(" ", " x", 1)), text=True),
    model_case("model-text-frames-rig", ("frames.txt", "line", "rig 3"),
               _text_line("frames.txt", 0, lambda line: line.split(" ", 1)[0] + " 3 " + line.split(" ", 2)[2]),
               text=True),
    model_case("model-gt-truncated", ("cameras.bin", "truncated"), _bytes("cameras.bin", lambda data: data[:10]),
               command="gt"),
    model_case("model-convert-truncated", ("points3D.bin", "truncated"),
               _bytes("points3D.bin", lambda data: data[:20]), command="convert"),
    Case("model-run-has-no-matches", lambda root, bases: _run_model(root, bases), ("model", "holds no matches")),
]


def _run_model(root: Path, bases: dict) -> list:
    shutil.copytree(bases["model"], root / "model")
    return ["run", root / "model", "-o", out(root)]


def _first_keypoint_nan(data: bytearray) -> bytearray:
    """images.bin: the first image's first keypoint x = NaN (after its NUL-terminated name)."""
    name_end = data.index(b"\0", IMAGE_POSE + 60)
    struct.pack_into("<d", data, name_end + 1 + 8, np.nan)
    return data


def _drop_first_frame_data(data: bytearray) -> bytearray:
    """frames.bin: the first frame lists no data (its image then is in no frame)."""
    offset = 8 + 4 + 4 + 56
    (count,) = struct.unpack_from("<I", data, offset)
    return data[:offset] + struct.pack("<I", 0) + data[offset + 4 + 16 * count:]


# ============================================================================ workspaces

def ws_case(name: str, expect: tuple[str, ...], edit: Callable[[Path, dict], None], stage: str = "average") -> Case:
    def build(root: Path, bases: dict) -> list:
        workspace = root / "ws"
        shutil.copytree(bases["workspace"], workspace)
        edit(workspace, bases)
        return [stage, workspace]

    return Case(name, build, expect)


def _state(change: Callable[[dict], None]) -> Callable[[Path, dict], None]:
    """Rewrite state.npz with its arrays changed (``change`` edits the name -> array dict)."""
    def edit(workspace: Path, bases: dict) -> None:
        with np.load(workspace / "state.npz", allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
        change(arrays)
        np.savez(workspace / "state.npz", **arrays)
    return edit


def _meta(change: Callable[[dict], None]) -> Callable[[dict], None]:
    def edit(arrays: dict) -> None:
        meta = json.loads(str(arrays["meta_json"]))
        change(meta)
        arrays["meta_json"] = np.array(json.dumps(meta))
    return edit


def _raw_state(content: Callable[[bytes], bytes]) -> Callable[[Path, dict], None]:
    def edit(workspace: Path, bases: dict) -> None:
        path = workspace / "state.npz"
        path.write_bytes(content(path.read_bytes()))
    return edit


def _zip_without(name: str) -> Callable[[Path, dict], None]:
    def edit(workspace: Path, bases: dict) -> None:
        path = workspace / "state.npz"
        with zipfile.ZipFile(path) as source:
            members = {info.filename: source.read(info) for info in source.infolist()}
        with zipfile.ZipFile(path, "w") as target:
            for member, payload in members.items():
                if member != f"{name}.npy":
                    target.writestr(member, payload)
    return edit


def _fifo_state(workspace: Path, bases: dict) -> None:
    (workspace / "state.npz").unlink()
    os.mkfifo(workspace / "state.npz")


def _input_elsewhere(path_of: Callable[[Path], Path]) -> Callable[[Path, dict], None]:
    """The workspace's input_path pointed at a (broken) copy of its database in the case folder."""
    def edit(workspace: Path, bases: dict) -> None:
        copy = path_of(workspace)
        _state(_meta(lambda meta: meta.update(input_path=str(copy))))(workspace, bases)
    return edit


def _smaller_input(workspace: Path) -> Path:
    copy = workspace.parent / "smaller.db"
    shutil.copyfile(HJ4_DB, copy)
    _edit_db(copy, "UPDATE keypoints SET rows = 5, data = substr(data, 1, 120)")
    return copy


def _broken_input(workspace: Path) -> Path:
    copy = workspace.parent / "broken.db"
    shutil.copyfile(HJ4_DB, copy)
    _edit_db(copy, "UPDATE cameras SET model = 123")
    return copy


STATE = "state.npz"
WS_CASES = [
    ws_case("ws-state-truncated", (STATE, "unreadable workspace state"),
            _raw_state(lambda data: data[: len(data) // 2])),
    ws_case("ws-state-not-zip", (STATE, "unreadable workspace state"), _raw_state(lambda data: b"not a zip file")),
    ws_case("ws-state-empty", (STATE, "unreadable workspace state"), _raw_state(lambda data: b"")),
    ws_case("ws-state-fifo", (STATE, "named pipe"), _fifo_state),
    ws_case("ws-state-missing-meta", (STATE, "meta_json", "missing"), _zip_without("meta_json")),
    ws_case("ws-state-missing-matches", (STATE, "matches", "missing"), _zip_without("matches")),
    ws_case("ws-meta-without-views", (STATE, "meta_json.views", "missing"), _state(_meta(lambda m: m.pop("views")))),
    ws_case("ws-meta-views-wrong", (STATE, "meta_json.views[0]"), _state(_meta(lambda m: m["views"][0].pop()))),
    ws_case("ws-meta-input-kind", (STATE, "meta_json.input_kind"),
            _state(_meta(lambda m: m.update(input_kind="pdf")))),
    ws_case("ws-meta-edges-count", (STATE, "meta_json.edges", "the arrays hold"),
            _state(_meta(lambda m: m["edges"].pop()))),
    ws_case("ws-meta-not-json", (STATE, "meta_json", "malformed JSON"),
            _state(lambda arrays: arrays.update(meta_json=np.array("{not json")))),
    ws_case("ws-meta-deep", (STATE, "meta_json", "nested"),
            _state(lambda arrays: arrays.update(meta_json=np.array(DEEP)))),
    ws_case("ws-meta-stages-numbers", (STATE, "meta_json.stages"), _state(_meta(lambda m: m.update(stages=[1, 2])))),
    ws_case("ws-rotations-half-nan", (STATE, "rotations", "finite or all NaN"),
            _state(lambda arrays: arrays["rotations"].__setitem__((0, 0, 0), np.nan)), stage="optimize"),
    ws_case("ws-rotations-shape", (STATE, "rotations", "shape (2, 3, 3)"),
            _state(lambda arrays: arrays.update(rotations=arrays["rotations"][:2])), stage="optimize"),
    ws_case("ws-offsets-decreasing", (STATE, "match_offsets"),
            _state(lambda arrays: arrays["match_offsets"].__setitem__(1, 10**9))),
    ws_case("ws-matches-negative", (STATE, "matches", "negative"),
            _state(lambda arrays: arrays["matches"].__setitem__((0, 0), -4))),
    ws_case("ws-matches-float", (STATE, "matches", "shape"),
            _state(lambda arrays: arrays.update(matches=arrays["matches"].astype(float)))),
    ws_case("ws-edge-unknown-view", (STATE, "edge_views", "not a pair"),
            _state(lambda arrays: arrays["edge_views"].__setitem__((0, 1), 99))),
    ws_case("ws-relative-rotation-nan", (STATE, "R_j_from_i", "not finite"),
            _state(lambda arrays: arrays["R_j_from_i"].__setitem__((0, 0, 0), np.nan))),
    ws_case("ws-input-inconsistent", ("smaller.db", "two_view_geometries", "keypoint index"),
            _input_elsewhere(_smaller_input)),
    ws_case("ws-matches-beyond-input-keypoints", (STATE, "matches", "changed since"),
            _state(lambda arrays: arrays["matches"].__setitem__((0, 0), 10**7))),
    ws_case("ws-input-broken", ("broken.db", "cameras: camera 1", "unknown camera model id 123"),
            _input_elsewhere(_broken_input)),
    ws_case("ws-not-a-workspace", ("not a rotonly workspace",), lambda workspace, bases: (workspace / STATE).unlink()),
]


# ============================================================================ destinations (-o)

def _good_db_to(destination: Callable[[Path], Path]) -> Callable[[Path, dict], list]:
    def build(root: Path, bases: dict) -> list:
        return ["run", _db(root, HJ4_DB), "-o", destination(root)]
    return build


def _file(root: Path, name: str = "file.txt") -> Path:
    (root / name).write_text("a file")
    return root / name


def _foreign(root: Path) -> Path:
    (root / "thesis").mkdir()
    (root / "thesis" / "thesis.tex").write_text("precious")
    return root / "thesis"


def _input_inside_out(root: Path, bases: dict) -> list:
    shutil.copytree(bases["workspace"], root / "ws")
    path = _db(root / "ws", HJ4_DB, "input.db")
    return ["run", path, "-o", root / "ws"]


DESTINATION_CASES = [
    Case("out-parent-is-a-file", _good_db_to(lambda root: _file(root) / "sub" / "OUT"),
         ("file.txt", "-o", "is not a folder")),
    Case("out-is-a-file", _good_db_to(lambda root: _file(root, "OUT")), ("OUT", "-o", "not a folder")),
    Case("out-holds-foreign-files", _good_db_to(_foreign), ("thesis", "-o", "not a rotonly workspace")),
    Case("out-parent-broken-link", _good_db_to(lambda root: _broken_link(root) / "OUT"),
         ("dangling", "-o", "broken symbolic link")),
    Case("out-holds-the-input", _input_inside_out, ("input.db", "-o", "inside OUT")),
    Case("eval-out-parent-is-a-file", lambda root, bases: ["eval", "--gt", HJ, ESTIMATE, "-o",
                                                           _file(root) / "report"], ("file.txt", "not a folder")),
]


def _broken_link(root: Path) -> Path:
    os.symlink(root / "nowhere", root / "dangling")
    return root / "dangling"


# ============================================================================ usage


def usage_case(name: str, expect: tuple[str, ...], *options: str, command: str = "run") -> Case:
    def build(root: Path, bases: dict) -> list:
        return [command, _db(root, HJ4_DB), "-o", out(root), *options]

    return Case(name, build, expect)


USAGE_CASES = [
    usage_case("usage-seed-negative", ("rotonly run", "--seed", "-1"), "--seed", "-1"),
    usage_case("usage-max-residual-nan", ("--max-residual-deg", "not a finite number"), "--max-residual-deg", "nan"),
    usage_case("usage-ransac-error-inf", ("--ransac-max-error", "not a finite number"), "--ransac-max-error", "inf"),
    usage_case("usage-min-inliers-too-few", ("--min-inliers", "2"), "--min-inliers", "2"),
    usage_case("usage-jobs-zero", ("--jobs", "0"), "--jobs", "0"),
    usage_case("usage-unknown-option", ("No such option", "--bogus"), "--bogus"),
    usage_case("usage-identify-seed-text", ("rotonly identify", "--seed"), "--seed", "x", command="identify"),
    Case("usage-missing-output", lambda root, bases: ["run", _db(root, HJ4_DB)], ("Missing option", "-o")),
]

CASES: list[Case] = [*DB_CASES, *FILE_CASES, *SPECIAL_CASES, *MVG_CASES, *GT_CASES, *MODEL_CASES, *WS_CASES,
                     *DESTINATION_CASES, *USAGE_CASES]
