"""The bad-input corpus (tests/corpus.py), its first half: the ``Case`` and what the cases share,
and the broken inputs: COLMAP databases, other files, special files, OpenMVG projects."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import struct
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

def copy_db(root: Path, base: Path = HJ_DB, name: str = "database.db") -> Path:
    path = root / name
    shutil.copyfile(base, path)
    return path


def edit_db(path: Path, *statements) -> None:
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
        path = copy_db(root, base)
        edit_db(path, *statements)
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
