"""Stage `refine`: TRRM (paper Alg. 2) on every active edge (lock-step batched LM), one chunk
of edges of about runtime.parallel.STAGE_CHUNK_MATCHES matches at a time (TRRM is per edge).

``trrm.refine`` also re-identifies each edge at its refined rotation (PR/B/I is decided
there), so the kind filter (``scene.view_graph.filter_rotation_singular``) is applied again afterwards.
"""

from __future__ import annotations

import logging
import time
from functools import partial

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.identification import IdentificationOptions
from rotonly_cli.geometry.trrm import TRRMOptions, refine
from rotonly_cli.scene.view_graph import (
    ViewGraph,
    filter_rotation_singular,
    kind_counts,
    kinds_text,
)
from rotonly_cli.stages import map_graph_edges

logger = logging.getLogger(__name__)
#: matches per --cluster task: TRRM takes ~1.1 us per match (the 200-view recipe's 4.4 M
#: matches in 4.8 s), so one chunk of 2^19 matches is ~0.6 s of work
CLUSTER_TASK_MATCHES = 1 << 19


def refine_edges(graph: ViewGraph, normalized: dict[int, np.ndarray], options: TRRMOptions = TRRMOptions(),
                 identification_options: IdentificationOptions = IdentificationOptions(), jobs: int = 1) -> dict:
    """Refine R_j_from_i and t_dir of the active edges in place; returns the report.
    ``jobs`` > 1: the edges are split over forked processes where that is safe and pays
    (rotonly_cli.runtime.parallel); the report says how many parts ran."""
    start = time.perf_counter()
    edges = graph.active_edges()
    report: dict = {"num_edges": len(edges)}
    if edges:
        R0 = np.stack([graph.edges[k].R_j_from_i for k in edges])
        fn = partial(refine, options=options, identification_options=identification_options)
        # --cluster: tasks of CLUSTER_TASK_MATCHES (runtime/cluster.py); else forked processes
        result, report["processes"] = map_graph_edges("refine", fn, graph, normalized, edges, R0, jobs,
                                                      CLUSTER_TASK_MATCHES)
        change = np.degrees(so3.geodesic_angle(result.rotations, R0))
        for row, k in enumerate(edges):
            edge = graph.edges[k]
            edge.R_j_from_i = result.rotations[row]
            edge.t_dir = result.translation_directions[row]
            edge.scene_kind = result.kinds[row].value
            edge.detection_value = float(result.identification.detection_value[row])
            edge.pure_rotation_ratio = float(result.identification.pure_rotation_ratio[row])
            edge.trrm_initial_cost = float(result.initial_cost[row])
            edge.trrm_cost = float(result.cost[row])
            edge.trrm_iterations = int(result.iterations[row])
            edge.trrm_rotation_change_deg = float(change[row])
        report.update({
            "cost_before": float(result.initial_cost.sum()), "cost_after": float(result.cost.sum()),
            "iterations_max": int(result.iterations.max()), "num_converged": int(result.converged.sum()),
            "rotation_change_deg": {"mean": float(change.mean()), "median": float(np.median(change)),
                                    "max": float(change.max())},
        })
    report["kinds"] = kind_counts(graph, edges)
    report["num_filtered_rotation_singular"] = filter_rotation_singular(graph)
    report["num_active_edges"] = len(graph.active_edges())
    report["unregistered_views"] = list(graph.unregistered_views)
    report["time_s"] = time.perf_counter() - start
    logger.info("refine (TRRM): %d edges (%s), cost %.4g -> %.4g, median rotation change %.4f deg",
                len(edges), kinds_text(report["kinds"]), report.get("cost_before", 0.0), report.get("cost_after", 0.0),
                report.get("rotation_change_deg", {}).get("median", 0.0))
    return report
