"""The bad-input corpus (tests/corpus.py), its second half: the models rotonly reads besides its
input (Strecha ground truths, COLMAP models, workspaces of the stage commands), destinations (-o)
and usage."""

from __future__ import annotations

import json
import os
import shutil
import struct
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from corpus_inputs import DEEP, ESTIMATE, HJ, HJ4_DB, HUGE, Case, copy_db, edit_db, out

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
        return ["run", copy_db(root), "-o", out(root), "--gt", gt]

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
    Case("gt-missing", lambda root, bases: ["run", copy_db(root), "-o", out(root), "--gt", root / "nothing"],
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
    return ["run", copy_db(root), "-o", out(root), "--gt", root / "gt.json"]


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
            return ["run", copy_db(root), "-o", out(root), "--gt", model]
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
    edit_db(copy, "UPDATE keypoints SET rows = 5, data = substr(data, 1, 120)")
    return copy


def _broken_input(workspace: Path) -> Path:
    copy = workspace.parent / "broken.db"
    shutil.copyfile(HJ4_DB, copy)
    edit_db(copy, "UPDATE cameras SET model = 123")
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
        return ["run", copy_db(root, HJ4_DB), "-o", destination(root)]
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
    path = copy_db(root / "ws", HJ4_DB, "input.db")
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
        return [command, copy_db(root, HJ4_DB), "-o", out(root), *options]

    return Case(name, build, expect)


USAGE_CASES = [
    usage_case("usage-seed-negative", ("rotonly run", "--seed", "-1"), "--seed", "-1"),
    usage_case("usage-max-residual-nan", ("--max-residual-deg", "not a finite number"), "--max-residual-deg", "nan"),
    usage_case("usage-ransac-error-inf", ("--ransac-max-error", "not a finite number"), "--ransac-max-error", "inf"),
    usage_case("usage-min-inliers-too-few", ("--min-inliers", "2"), "--min-inliers", "2"),
    usage_case("usage-jobs-zero", ("--jobs", "0"), "--jobs", "0"),
    usage_case("usage-unknown-option", ("No such option", "--bogus"), "--bogus"),
    usage_case("usage-identify-seed-text", ("rotonly identify", "--seed"), "--seed", "x", command="identify"),
    Case("usage-missing-output", lambda root, bases: ["run", copy_db(root, HJ4_DB)], ("Missing option", "-o")),
]
