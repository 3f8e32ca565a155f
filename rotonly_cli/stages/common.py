"""Small helpers shared by the pipeline stages: edge batches, view indexing, reports."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from rotonly_cli.geometry import twoview as tv
from rotonly_cli.io import atomic
from rotonly_cli.io.viewgraph import ViewGraph


def edge_batch(graph: ViewGraph, normalized: dict[int, np.ndarray], edges: list[int]) -> tv.EdgeBatch:
    """EdgeBatch (z = 1 normalized coordinates) of the matches of ``edges``, in that order."""
    if not edges:
        return tv.EdgeBatch(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(1, dtype=np.int64))
    x_i = np.concatenate([normalized[graph.edges[k].i][graph.edges[k].matches[:, 0]] for k in edges])
    x_j = np.concatenate([normalized[graph.edges[k].j][graph.edges[k].matches[:, 1]] for k in edges])
    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    return tv.pack_flat(x_i, x_j, np.concatenate([[0], np.cumsum(counts)]))


def view_index(graph: ViewGraph) -> dict[int, int]:
    """view id -> row of the (n, ...) rotation / centre arrays (sorted view ids)."""
    return {v: k for k, v in enumerate(graph.view_ids())}


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
