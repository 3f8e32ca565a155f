"""Stage `identify`: scene identification of every active edge (paper §"Scene Identification").

Batched over the edges (``geometry.identification.identify``), one chunk of about
runtime.parallel.STAGE_CHUNK_MATCHES matches at a time (every number is per edge). Filter: ROTATION_SINGULAR edges
(Holoplane / RankRegular-line) are excluded, as the paper says — their rotation is not
determined by the matches. PURE_ROTATION edges stay active: they keep their rotation for
averaging but give no translation constraint (``stages.translate`` uses REGULAR edges only).
"""

from __future__ import annotations

import logging
import time
from functools import partial

import numpy as np

from rotonly_cli.geometry.identification import IdentificationOptions, identify
from rotonly_cli.scene.view_graph import (
    ViewGraph,
    filter_rotation_singular,
    kind_counts,
    kinds_text,
)
from rotonly_cli.stages import map_graph_edges

logger = logging.getLogger(__name__)
#: matches per --cluster task: identification takes ~0.25 us per match (the 200-view recipe's
#: 4.4 M matches in 1.1 s), so 2^21 matches are ~0.5 s of work
CLUSTER_TASK_MATCHES = 1 << 21


def identify_edges(graph: ViewGraph, normalized: dict[int, np.ndarray],
                   options: IdentificationOptions = IdentificationOptions(), jobs: int = 1) -> dict:
    """Set scene_kind / detection values of the active edges at their current rotations.
    ``jobs`` > 1: over forked processes where that is safe and pays (rotonly_cli.runtime.parallel)."""
    start = time.perf_counter()
    edges = graph.active_edges()
    processes = 1
    if edges:
        R = np.stack([graph.edges[k].R_j_from_i for k in edges])
        # --cluster: tasks of CLUSTER_TASK_MATCHES (runtime/cluster.py); else forked processes
        result, processes = map_graph_edges("identify", partial(identify, options=options), graph, normalized, edges,
                                            R, jobs, CLUSTER_TASK_MATCHES)
        for row, k in enumerate(edges):
            edge = graph.edges[k]
            edge.scene_kind = result.kinds[row].value
            edge.detection_value = float(result.detection_value[row])
            edge.pure_rotation_ratio = float(result.pure_rotation_ratio[row])
    counts = kind_counts(graph, edges)
    num_singular = filter_rotation_singular(graph)
    logger.info("identify: %d edges (%s); %d rotation-singular filtered", len(edges), kinds_text(counts), num_singular)
    return {"num_edges": len(edges), "kinds": counts, "num_filtered_rotation_singular": num_singular,
            "num_active_edges": len(graph.active_edges()), "unregistered_views": list(graph.unregistered_views),
            "rotation_singular_threshold": options.rotation_singular_threshold,
            "pure_rotation_ratio_sigmas": options.pure_rotation_ratio_sigmas,
            "processes": processes, "time_s": time.perf_counter() - start}
