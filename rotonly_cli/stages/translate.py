"""Stage `translate`: camera centres by LiGT from the global rotations and the tracks of the
active REGULAR edges (PURE_ROTATION edges carry no translation information, paper
§"Scene Identification"). Views LiGT cannot constrain get NaN centres (not registered)."""

from __future__ import annotations

import logging
import time

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.ligt import LiGTOptions, ligt_translations
from rotonly_cli.scene.tracks import TrackCache, graph_tracks
from rotonly_cli.scene.view_graph import ViewGraph, regular_edges, view_index

logger = logging.getLogger(__name__)


def translate_graph(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                    options: LiGTOptions | None = None,
                    track_cache: TrackCache | None = None) -> tuple[np.ndarray, dict]:
    """(centres (n, 3), NaN where unknown; report). ``track_cache``: the run's, shared
    with triangulate (scene/tracks)."""
    start = time.perf_counter()
    index = view_index(graph)
    registered = np.all(np.isfinite(R_cam_from_world.reshape(len(index), -1)), axis=1)
    edges = [k for k in regular_edges(graph) if registered[index[graph.edges[k].i]]
             and registered[index[graph.edges[k].j]]]
    if not edges:
        raise AlgorithmError("translation: no REGULAR edge between registered views (all pure rotation?)")
    R = np.where(registered[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, normalized, edges, R, cache=track_cache)
    result = ligt_translations(R, tracks.track_id, tracks.view, obs_xy, view_mask=registered, options=options)
    centers = np.where(result.has_translation[:, None], result.centers, np.nan)
    ids = graph.view_ids()
    without = [ids[r] for r in np.flatnonzero(registered & ~result.has_translation)]
    report = {"num_edges": len(edges), "num_tracks": tracks.num_tracks, "num_observations": tracks.num_observations,
              "num_inconsistent_tracks": tracks.num_inconsistent,
              "num_views_with_centre": int(result.has_translation.sum()),
              "views_without_centre": without, "smallest_eigenvalues": result.smallest_eigenvalues.tolist(),
              "sign_votes": list(result.sign_votes), "time_s": time.perf_counter() - start}
    logger.info("translate (LiGT): %d tracks from %d REGULAR edges, %d views with a centre%s",
                tracks.num_tracks, len(edges), report["num_views_with_centre"],
                f", {len(without)} without" if without else "")
    return centers, report
