"""The ``OUT/`` workspace files shared by ``rotonly run`` and the stage subcommands:
``state.npz``, ``view_graph.json`` and ``reports/<stage>.json`` (formats: docs/formats.md §7).

``OUT/state.npz`` holds what a later stage needs and cannot cheaply recompute: the input it
came from (re-read for keypoints, intrinsics and images), the view graph (every edge's pose,
matches, status and diagnostics) and the current global rotations / centres. Arrays are
stored flat (matches concatenated with offsets); edge diagnostics as one JSON string.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.io.inputs import open_input, parse_json
from rotonly_cli.scene.types import View
from rotonly_cli.scene.view_graph import Edge, ViewGraph

STATE_FILE = "state.npz"
_EDGE_FIELDS = ("pose_source", "config", "scene_kind", "detection_value", "pure_rotation_ratio", "status",
                "reason", "residual_deg", "trrm_initial_cost", "trrm_cost", "trrm_iterations",
                "trrm_rotation_change_deg", "dropped_matches")


@dataclass
class WorkspaceState:
    input_path: str
    input_kind: str  # "colmap-db" | "openmvg"
    matches_dir: str | None
    image_path: str | None
    graph: ViewGraph
    #: (n, 3, 3) R_cam_from_world per view in ``graph.view_ids()`` order; NaN = not estimated
    rotations: np.ndarray | None = None
    centers: np.ndarray | None = None  # (n, 3); NaN = not estimated
    stages: list[str] = field(default_factory=list)  # stages done, in order
    options: dict = field(default_factory=dict)  # options of the run (for later stages)


def save_state(out_dir: str | os.PathLike, state: WorkspaceState) -> Path:
    """Write ``out_dir/state.npz`` atomically."""
    out_dir = Path(out_dir)
    graph = state.graph
    view_ids = graph.view_ids()
    counts = np.array([edge.num_inliers for edge in graph.edges], dtype=np.int64)
    meta = {
        "input_path": state.input_path, "input_kind": state.input_kind, "matches_dir": state.matches_dir,
        "image_path": state.image_path, "stages": state.stages, "options": state.options,
        "views": [[v, graph.views[v].name, graph.views[v].intrinsics_id] for v in view_ids],
        "unregistered_views": graph.unregistered_views,
        "edges": [{name: _jsonable(getattr(edge, name)) for name in _EDGE_FIELDS} for edge in graph.edges],
    }
    n = len(view_ids)
    arrays = {
        "meta_json": np.array(json.dumps(meta, sort_keys=True)),
        "edge_views": np.array([[e.i, e.j] for e in graph.edges], dtype=np.int64).reshape(-1, 2),
        "R_j_from_i": np.array([e.R_j_from_i for e in graph.edges], dtype=float).reshape(-1, 3, 3),
        "t_dir": np.array([e.t_dir for e in graph.edges], dtype=float).reshape(-1, 3),
        "match_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "matches": [edge.matches for edge in graph.edges],  # (M, 2) int64, written edge by edge
        "rotations": (np.full((n, 3, 3), np.nan) if state.rotations is None else state.rotations),
        "centers": (np.full((n, 3), np.nan) if state.centers is None else state.centers),
    }
    with atomic.file_path(out_dir / STATE_FILE, suffix=".npz") as temporary:
        _write_npz(temporary, arrays)
    return out_dir / STATE_FILE


def _write_npz(path, arrays: dict) -> None:
    """``np.savez(path, **arrays)``, byte for byte, where a list of (m_k, 2) integer arrays
    stands for their concatenation as int64: written part by part, so that all matches are
    never copied at once (np.concatenate(...).astype(np.int64) held two copies)."""
    with zipfile.ZipFile(os.fspath(path), mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            with archive.open(name + ".npy", "w", force_zip64=True) as stream:
                if not isinstance(value, list):
                    np.lib.format.write_array(stream, np.asanyarray(value))
                    continue
                rows = sum(part.shape[0] for part in value)
                np.lib.format.write_array_header_1_0(stream, {"descr": np.lib.format.dtype_to_descr(
                    np.dtype(np.int64)), "fortran_order": False, "shape": (rows, 2)})
                for part in value:
                    stream.write(np.ascontiguousarray(part, dtype="<i8").reshape(-1, 2).data)


def _jsonable(value):
    if isinstance(value, (float, np.floating)):
        return None if not np.isfinite(value) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


#: state.npz arrays: name -> (dtype kind, shape with "E" edges, "E+1", "M" matches, "n" views)
_STATE_ARRAYS = {
    "meta_json": ("U", ()), "edge_views": ("i", ("E", 2)), "R_j_from_i": ("f", ("E", 3, 3)),
    "t_dir": ("f", ("E", 3)), "match_offsets": ("i", ("E+1",)), "matches": ("i", ("M", 2)),
    "rotations": ("f", ("n", 3, 3)), "centers": ("f", ("n", 3)),
}
#: meta_json keys -> their JSON types
_META_TYPES = {"input_path": str, "input_kind": str, "matches_dir": (str, type(None)),
               "image_path": (str, type(None)), "stages": list, "options": dict, "views": list,
               "unregistered_views": list, "edges": list}


def load_state(out_dir: str | os.PathLike) -> WorkspaceState:
    """Read ``out_dir/state.npz``; InputError (naming the file and the array or key) if
    ``out_dir`` is not a rotonly workspace or its state is truncated or inconsistent."""
    path = Path(out_dir) / STATE_FILE
    if not os.path.lexists(path):
        raise InputError(f"not a rotonly workspace (no {STATE_FILE}; run `rotonly identify INPUT -o OUT` first)",
                         path=str(out_dir))
    arrays = _state_arrays(path)
    meta = arrays.pop("meta")
    views = meta["views"]
    view_ids = {int(v[0]) for v in views}
    for i, j in arrays["edge_views"].tolist():
        if not (i < j and i in view_ids and j in view_ids):
            raise InputError(f"edge ({i}, {j}) is not a pair of the workspace's views (smaller id first)",
                             path=str(path), field="edge_views")
    graph = ViewGraph(views={int(v): View(int(v), name, int(intr)) for v, name, intr in views},
                      unregistered_views=[int(v) for v in meta["unregistered_views"]])
    offsets = arrays["match_offsets"]
    for k, fields in enumerate(meta["edges"]):
        i, j = (int(v) for v in arrays["edge_views"][k])
        edge = Edge(i, j, arrays["R_j_from_i"][k].copy(), arrays["t_dir"][k].copy(),
                    arrays["matches"][offsets[k]:offsets[k + 1]].copy())
        for name, value in fields.items():
            setattr(edge, name, float("nan") if value is None and name not in ("config", "scene_kind") else value)
        graph.edges.append(edge)
    rotations = arrays["rotations"]
    centers = arrays["centers"]
    return WorkspaceState(meta["input_path"], meta["input_kind"], meta["matches_dir"], meta["image_path"], graph,
                          None if np.all(np.isnan(rotations)) else rotations,
                          None if np.all(np.isnan(centers)) else centers, list(meta["stages"]),
                          dict(meta["options"]))


def _state_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays of state.npz, each of the dtype and shape of _STATE_ARRAYS, consistent
    with each other and with meta_json (offsets into the matches, one row per view), and
    the parsed meta_json as ``meta``."""
    try:
        with open_input(path) as stream, np.load(stream, allow_pickle=False) as data:
            missing = [name for name in _STATE_ARRAYS if name not in data.files]
            if missing:
                raise InputError(f"array {missing[0]} is missing (truncated or not written by rotonly)",
                                 path=str(path), field=missing[0])
            arrays = {name: data[name] for name in _STATE_ARRAYS}
    except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"unreadable workspace state ({type(exc).__name__}: {exc})", path=str(path)) from None
    if arrays["meta_json"].dtype.kind != "U" or arrays["meta_json"].shape != ():
        raise InputError("expected one string", path=str(path), field="meta_json")
    meta = parse_json(str(arrays["meta_json"]), path, "meta_json")
    _check_meta(path, meta, len(arrays["edge_views"]))
    sizes = {"E": len(arrays["edge_views"]), "M": len(arrays["matches"]), "n": len(meta["views"])}
    sizes["E+1"] = sizes["E"] + 1
    for name, (kind, shape) in _STATE_ARRAYS.items():
        array = arrays[name]
        expected = tuple(sizes.get(d, d) for d in shape)
        if array.dtype.kind != kind or array.shape != expected:
            raise InputError(f"{array.dtype} array of shape {array.shape}, expected {kind} of shape {expected}",
                             path=str(path), field=name)
    offsets = arrays["match_offsets"]
    if offsets[0] != 0 or offsets[-1] != sizes["M"] or np.any(np.diff(offsets) < 0):
        raise InputError("not increasing from 0 to the number of matches", path=str(path), field="match_offsets")
    if np.any(arrays["matches"] < 0):
        raise InputError("negative keypoint index", path=str(path), field="matches")
    for name in ("R_j_from_i", "t_dir"):
        if not np.all(np.isfinite(arrays[name])):
            raise InputError("not finite", path=str(path), field=name)
    for name in ("rotations", "centers"):
        rows = arrays[name].reshape(sizes["n"], -1)
        finite = np.isfinite(rows)
        if not np.all(finite.all(axis=1) | np.isnan(rows).all(axis=1)):
            raise InputError("rows must be finite or all NaN (not estimated)", path=str(path), field=name)
    arrays["meta"] = meta
    return arrays


def _check_meta(path: Path, meta, num_edges: int) -> None:
    """meta_json: an object with the keys and types of _META_TYPES, views [id, name,
    intrinsics id], one diagnostics object per edge; edges between listed views."""
    def fail(field: str, message: str) -> InputError:
        return InputError(message, path=str(path), field=f"meta_json.{field}")

    if not isinstance(meta, dict):
        raise InputError("expected a JSON object", path=str(path), field="meta_json")
    for key, kind in _META_TYPES.items():
        if key not in meta:
            raise fail(key, "missing")
        if not isinstance(meta[key], kind):
            raise fail(key, f"expected {getattr(kind, '__name__', 'a string or null')}, got "
                            f"{type(meta[key]).__name__}")
    if meta["input_kind"] not in ("colmap-db", "openmvg"):
        raise fail("input_kind", f"{meta['input_kind'][:40]!r}: expected colmap-db or openmvg")
    if not all(isinstance(stage, str) for stage in meta["stages"]):
        raise fail("stages", "expected stage names")
    for k, view in enumerate(meta["views"]):
        if not (isinstance(view, list) and len(view) == 3 and _is_int(view[0]) and isinstance(view[1], str)
                and _is_int(view[2])):
            raise fail(f"views[{k}]", "expected [id, name, intrinsics id]")
    if not all(_is_int(v) for v in meta["unregistered_views"]):
        raise fail("unregistered_views", "expected view ids")
    if len(meta["edges"]) != num_edges:
        raise fail("edges", f"{len(meta['edges'])} edges, the arrays hold {num_edges}")
    for k, fields in enumerate(meta["edges"]):
        if not isinstance(fields, dict) or not set(fields) <= set(_EDGE_FIELDS):
            raise fail(f"edges[{k}]", f"expected an object with the keys {', '.join(_EDGE_FIELDS)}")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_graph_fits(graph: ViewGraph, scene, path: str | os.PathLike) -> None:
    """InputError unless every view and keypoint the workspace's edges use is in ``scene``
    (the input re-read by a stage command: a workspace stays valid only while its input does)."""
    for edge in graph.edges:
        for view_id, column in ((edge.i, 0), (edge.j, 1)):
            if view_id not in graph.views or view_id not in scene.views:
                raise InputError(f"edge ({edge.i}, {edge.j}) uses view {view_id}, which the input does not hold",
                                 path=str(path), field="edge_views")
            count = len(scene.keypoints.get(view_id, ()))
            if len(edge.matches) and edge.matches[:, column].max() >= count:
                raise InputError(f"edge ({edge.i}, {edge.j}) uses keypoint {int(edge.matches[:, column].max())} of "
                                 f"view {view_id}, which has {count} in the input (changed since?)",
                                 path=str(path), field="matches")


def view_graph_document(graph: ViewGraph) -> dict:
    return {
        "views": [{"id": int(v), "name": graph.views[v].name} for v in graph.view_ids()],
        "unregistered_views": [int(v) for v in graph.unregistered_views],
        "counts": graph.counts(),
        "edges": [edge.diagnostics() for edge in graph.edges],
    }


def write_view_graph_json(path: str | os.PathLike, graph: ViewGraph) -> None:
    """Per-edge diagnostics as JSON (sorted keys, fixed edge order: deterministic bytes)."""
    atomic.write_text(path, json.dumps(view_graph_document(graph), indent=1, sort_keys=True) + "\n")


def _clean(value):
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_report(out_dir: str | os.PathLike, stage: str, report: dict) -> Path:
    """``out_dir/reports/<stage>.json`` (sorted keys)."""
    path = Path(out_dir) / "reports" / f"{stage}.json"
    atomic.write_text(path, json.dumps(_clean(report), indent=1, sort_keys=True) + "\n")
    return path


def read_report(out_dir: str | os.PathLike, stage: str) -> dict | None:
    """``out_dir/reports/<stage>.json`` as written by :func:`write_report`; None when absent or
    not a JSON object (a report is a record, never an input the run depends on for its data)."""
    path = Path(out_dir) / "reports" / f"{stage}.json"
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) else None
