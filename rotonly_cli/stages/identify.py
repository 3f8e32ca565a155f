"""Stage `identify`: scene identification of every active edge (paper §"Scene Identification").

Batched over all edges (``geometry.scene.identify``). Filter: ROTATION_SINGULAR edges
(Holoplane / RankRegular-line) are excluded, as the paper says — their rotation is not
determined by the matches. PURE_ROTATION edges stay active: they keep their rotation for
averaging but give no translation constraint (``stages.translate`` uses REGULAR edges only).
"""

from __future__ import annotations

import logging
import time
from functools import partial

import numpy as np

from rotonly_cli.geometry.scene import IdentificationOptions, SceneKind, identify
from rotonly_cli.io.viewgraph import ViewGraph, largest_component
from rotonly_cli.parallel import map_edges, plan
from rotonly_cli.stages.common import edge_batch

logger = logging.getLogger(__name__)

SINGULAR_REASON = "rotation singular (Holoplane / RankRegular-line)"


def apply_kind_filter(graph: ViewGraph) -> int:
    """Filter ROTATION_SINGULAR edges and re-check the largest component; returns the count."""
    count = 0
    for k in graph.active_edges():
        if graph.edges[k].scene_kind == SceneKind.ROTATION_SINGULAR.value:
            graph.edges[k].filter(SINGULAR_REASON)
            count += 1
    largest_component(graph)
    return count


def kind_counts(graph: ViewGraph, edges: list[int]) -> dict:
    counts = {kind.value: 0 for kind in SceneKind}
    for k in edges:
        counts[graph.edges[k].scene_kind] = counts.get(graph.edges[k].scene_kind, 0) + 1
    return counts


def identify_edges(graph: ViewGraph, normalized: dict[int, np.ndarray],
                   options: IdentificationOptions = IdentificationOptions(), jobs: int = 1) -> dict:
    """Set scene_kind / detection values of the active edges at their current rotations.
    ``jobs`` > 1: over forked processes where that is safe and pays (rotonly_cli.parallel)."""
    start = time.perf_counter()
    edges = graph.active_edges()
    processes = 1
    if edges:
        batch = edge_batch(graph, normalized, edges)
        R = np.stack([graph.edges[k].R_j_from_i for k in edges])
        ranges = plan(batch, jobs)
        processes = len(ranges)
        with np.errstate(all="ignore"):  # handled corner cases (twoview._quiet)
            result = map_edges(partial(identify, options=options), R, batch, ranges)
        for row, k in enumerate(edges):
            edge = graph.edges[k]
            edge.scene_kind = result.kinds[row].value
            edge.detection_value = float(result.detection_value[row])
            edge.pure_rotation_ratio = float(result.pure_rotation_ratio[row])
    counts = kind_counts(graph, edges)
    num_singular = apply_kind_filter(graph)
    logger.info("identify: %d edges: %s; %d rotation-singular filtered", len(edges), counts, num_singular)
    return {"num_edges": len(edges), "kinds": counts, "num_filtered_rotation_singular": num_singular,
            "num_active_edges": len(graph.active_edges()), "unregistered_views": list(graph.unregistered_views),
            "rotation_singular_threshold": options.rotation_singular_threshold,
            "pure_rotation_ratio_threshold": options.pure_rotation_ratio_threshold,
            "processes": processes, "time_s": time.perf_counter() - start}
