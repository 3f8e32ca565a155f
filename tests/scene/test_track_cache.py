"""graph_tracks with a TrackCache reuses the tracks of its previous call only for the same pairs and
matches; without one it always builds."""

from __future__ import annotations

import numpy as np

from rotonly_cli.geometry.tracks import build_tracks
from rotonly_cli.scene.tracks import TrackCache, graph_tracks
from rotonly_cli.scene.types import View
from rotonly_cli.scene.view_graph import Edge, ViewGraph


def _graph(rng: np.random.Generator) -> tuple[ViewGraph, dict[int, np.ndarray]]:
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 1) for v in (2, 4, 7)})
    for i, j in ((2, 4), (2, 7), (4, 7)):
        matches = np.stack([rng.permutation(50)[:30], rng.permutation(50)[:30]], axis=1)
        graph.edges.append(Edge(i, j, np.eye(3), np.zeros(3), matches))
    normalized = {v: rng.normal(size=(50, 2)) for v in (2, 4, 7)}
    return graph, normalized


def test_graph_tracks_reuses_only_identical_inputs():
    graph, normalized = _graph(np.random.default_rng(0))
    cache = TrackCache()
    tracks, obs_xy = graph_tracks(graph, normalized, [0, 1, 2], cache=cache)
    expected = build_tracks([(0, 1), (0, 2), (1, 2)], [edge.matches for edge in graph.edges])
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.feature, expected.feature)
    assert tracks.num_tracks > 5
    again, obs_again = graph_tracks(graph, normalized, [0, 1, 2], cache=cache)
    assert again is tracks  # same pairs and matches: reused
    np.testing.assert_array_equal(obs_again, obs_xy)

    graph.edges[1].matches = graph.edges[1].matches[:-3]  # other matches: rebuilt
    changed, _ = graph_tracks(graph, normalized, [0, 1, 2], cache=cache)
    assert changed is not tracks
    rebuilt = build_tracks([(0, 1), (0, 2), (1, 2)], [edge.matches for edge in graph.edges])
    np.testing.assert_array_equal(changed.track_id, rebuilt.track_id)
    np.testing.assert_array_equal(changed.view, rebuilt.view)
    fewer_edges, _ = graph_tracks(graph, normalized, [0, 2], cache=cache)  # other pairs: rebuilt
    expected = build_tracks([(0, 1), (1, 2)], [graph.edges[0].matches, graph.edges[2].matches])
    assert fewer_edges is not changed and fewer_edges.num_observations == expected.num_observations
    np.testing.assert_array_equal(fewer_edges.feature, expected.feature)
    assert expected.num_observations != changed.num_observations


def test_graph_tracks_without_a_cache_builds_every_time():
    graph, normalized = _graph(np.random.default_rng(1))
    first, _ = graph_tracks(graph, normalized, [0, 1, 2])
    second, _ = graph_tracks(graph, normalized, [0, 1, 2])
    assert second is not first
    np.testing.assert_array_equal(second.track_id, first.track_id)


def test_inlier_matches_weigh_edges_a_group_at_a_time(monkeypatch):
    from rotonly_cli.scene import tracks as scene_tracks

    rng = np.random.default_rng(3)
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 1) for v in (2, 4, 7)})
    centers = {2: np.zeros(3), 4: np.array([1.0, 0, 0]), 7: np.array([0, 1.0, 0])}
    points = rng.uniform(-2, 2, size=(50, 3)) + [0, 0, 8]
    normalized = {v: (points - c)[:, :2] / (points - c)[:, 2:] for v, c in centers.items()}
    for i, j in ((2, 4), (2, 7), (4, 7)):
        matches = np.stack([np.arange(40), np.arange(40)], axis=1)
        if (i, j) == (2, 4):
            matches[:4, 1] = [3, 0, 1, 2]  # 4 wrong matches
        graph.edges.append(Edge(i, j, np.eye(3), np.zeros(3), matches))
    rotations = np.stack([np.eye(3)] * 3)
    whole = scene_tracks.inlier_matches(graph, normalized, [0, 1, 2], rotations)
    # some wrong match goes (the swapped points that stay near their epipolar line may stay), no right one
    assert len(whole[0]) < 40 and set(range(4, 40)) <= set(whole[0][:, 0].tolist())
    assert [len(m) for m in whole[1:]] == [40, 40]
    monkeypatch.setattr(scene_tracks, "MATCHES_PER_GROUP", 1)
    grouped = scene_tracks.inlier_matches(graph, normalized, [0, 1, 2], rotations)
    assert [m.tolist() for m in grouped] == [m.tolist() for m in whole]
    # an edge that keeps every match hands over its own array, not a copy
    assert grouped[1] is graph.edges[1].matches and grouped[2] is graph.edges[2].matches


def test_conflicts_are_handed_out_once_and_not_kept_in_the_cache():
    graph, normalized = _graph(np.random.default_rng(0))  # random matches: components see views twice
    cache = TrackCache()
    tracks, _ = graph_tracks(graph, normalized, [0, 1, 2], cache=cache, keep_conflicts=True)
    assert tracks.num_inconsistent > 0 and tracks.conflicts.num_components == tracks.num_inconsistent
    assert cache.last[1].conflicts is None  # the run's cache does not hold them
    again, _ = graph_tracks(graph, normalized, [0, 1, 2], cache=cache)
    assert again is cache.last[1] and again.conflicts is None
    np.testing.assert_array_equal(again.track_id, tracks.track_id)
    rebuilt, _ = graph_tracks(graph, normalized, [0, 1, 2], cache=cache, keep_conflicts=True)
    assert rebuilt.conflicts is not None and len(rebuilt.conflicts.edges) == len(tracks.conflicts.edges)
