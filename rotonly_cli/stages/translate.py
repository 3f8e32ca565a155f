"""Stage `translate`: camera centres by LiGT from the global rotations and the tracks of the
active REGULAR edges (PURE_ROTATION edges carry no translation information, paper
§"Scene Identification"). Views LiGT cannot constrain get NaN centres (not registered)."""

from __future__ import annotations

import logging
import time

import numpy as np

from rotonly_cli.errors import AlgorithmError
from rotonly_cli.geometry.ligt import LiGTOptions, robust_ligt_translations
from rotonly_cli.scene.tracks import TrackCache, graph_tracks
from rotonly_cli.scene.view_graph import ViewGraph, regular_edges, view_index

logger = logging.getLogger(__name__)


def translate_graph(graph: ViewGraph, normalized: dict[int, np.ndarray], R_cam_from_world: np.ndarray,
                    options: LiGTOptions | None = None, track_cache: TrackCache | None = None,
                    focal_px: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(centres (n, 3), NaN where unknown; report). ``track_cache``: the run's, shared
    with triangulate (scene/tracks). ``focal_px`` (n,): each view's focal length, the unit of
    the outlier threshold of the robust rounds (default 1000 px)."""
    start = time.perf_counter()
    index = view_index(graph)
    registered = np.all(np.isfinite(R_cam_from_world.reshape(len(index), -1)), axis=1)
    edges = [k for k in regular_edges(graph) if registered[index[graph.edges[k].i]]
             and registered[index[graph.edges[k].j]]]
    if not edges:
        raise AlgorithmError("translation: no REGULAR edge between registered views (all pure rotation?)")
    R = np.where(registered[:, None, None], R_cam_from_world, np.eye(3))
    tracks, obs_xy = graph_tracks(graph, normalized, edges, R, cache=track_cache)
    focal = np.full(len(index), 1000.0) if focal_px is None else np.where(np.isfinite(focal_px), focal_px, 1000.0)
    robust = robust_ligt_translations(R, tracks.track_id, tracks.view, obs_xy, focal[tracks.view],
                                      view_mask=registered, options=options)
    result = robust.result
    centers = np.where(result.has_translation[:, None], result.centers, np.nan)
    ids = graph.view_ids()
    without = [ids[r] for r in np.flatnonzero(registered & ~result.has_translation)]
    report = {"num_edges": len(edges), "num_tracks": tracks.num_tracks, "num_observations": tracks.num_observations,
              "num_inconsistent_tracks": tracks.num_inconsistent,
              "num_views_with_centre": int(result.has_translation.sum()),
              "views_without_centre": without, "smallest_eigenvalues": result.smallest_eigenvalues.tolist(),
              "sign_votes": list(result.sign_votes), "robust_rounds": robust.rounds,
              "num_observations_used": int(robust.keep.sum()),
              "num_observations_dropped": int(tracks.num_observations - robust.keep.sum()),
              "outlier_threshold_px": robust.threshold_px, "time_s": time.perf_counter() - start}
    for number, round_ in enumerate(robust.rounds, 1):
        logger.debug("translate round %d: %d observations, sigma %.3f px, threshold %.2f px, %d dropped, "
                     "%d re-admitted", number, round_["observations"], round_["sigma_px"], round_["threshold_px"],
                     round_["dropped"], round_["readmitted"])
    logger.info("translate (LiGT): %d tracks, %d REGULAR edges, %d views with a centre%s; %d of %d "
                "observations kept", tracks.num_tracks, len(edges),
                report["num_views_with_centre"], f", {len(without)} without" if without else "",
                report["num_observations_used"], tracks.num_observations)
    return centers, report
