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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
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
        "matches": (np.concatenate([e.matches for e in graph.edges]).astype(np.int64) if graph.edges
                    else np.zeros((0, 2), dtype=np.int64)),
        "rotations": (np.full((n, 3, 3), np.nan) if state.rotations is None else state.rotations),
        "centers": (np.full((n, 3), np.nan) if state.centers is None else state.centers),
    }
    with atomic.file_path(out_dir / STATE_FILE, suffix=".npz") as temporary:
        np.savez(temporary, **arrays)
    return out_dir / STATE_FILE


def _jsonable(value):
    if isinstance(value, (float, np.floating)):
        return None if not np.isfinite(value) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def load_state(out_dir: str | os.PathLike) -> WorkspaceState:
    """Read ``out_dir/state.npz``; InputError if ``out_dir`` is not a rotonly workspace."""
    path = Path(out_dir) / STATE_FILE
    if not path.is_file():
        raise InputError(f"not a rotonly workspace (no {STATE_FILE}; run `rotonly identify INPUT -o OUT` first)",
                         path=str(out_dir))
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
        meta = json.loads(str(arrays["meta_json"]))
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"unreadable workspace state ({exc})", path=str(path)) from None
    graph = ViewGraph(views={int(v): View(int(v), name, int(intr)) for v, name, intr in meta["views"]},
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
