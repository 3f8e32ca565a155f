"""The stages of the chain (chain/stages.py runs them; each module's docstring says what it does)."""

from __future__ import annotations

from collections.abc import Callable, Iterable

#: the stages of `rotonly run`, in chain order (chain/stages.py runs them)
STAGES = ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate")


def map_graph_edges(stage: str, fn: Callable, graph, normalized: dict, edges: list[int], R, jobs: int,
                    task_matches: int):
    """(``fn(R, batch)`` over the matches of the graph's ``edges``, where it ran): a per-edge
    stage's work through runtime.cluster.map_edges (the --cluster session in tasks of
    ``task_matches`` matches, else ``jobs`` forked processes, chunk by chunk), each batch built
    from the graph's edges as :func:`~rotonly_cli.scene.view_graph.edge_batch` builds it."""
    import numpy as np

    from rotonly_cli.runtime import cluster
    from rotonly_cli.scene.view_graph import batch_of_arrays, edge_arrays, edge_batch

    counts = np.array([graph.edges[k].num_inliers for k in edges], dtype=np.int64)
    return cluster.map_edges(stage, fn, R, counts, jobs, lambda e0, e1: edge_arrays(graph, edges[e0:e1]),
                             batch_of_arrays, normalized, lambda e0, e1: edge_batch(graph, normalized, edges[e0:e1]),
                             task_matches)


def listed(items: Iterable[str], max_shown: int = 8) -> str:
    """The first ``max_shown`` of ``items`` joined by commas, then " ..." if there are more: how
    the run's messages name views and edges."""
    items = list(items)
    return ", ".join(items[:max_shown]) + (" ..." if len(items) > max_shown else "")
