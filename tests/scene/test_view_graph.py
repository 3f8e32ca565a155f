"""scene.view_graph / io.workspace: components, filters with reasons, deterministic JSON, state round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.geometry import so3
from rotonly_cli.io.workspace import WorkspaceState, load_state, save_state, write_view_graph_json
from rotonly_cli.scene.types import View
from rotonly_cli.scene.view_graph import Edge, ViewGraph, bridge_edges, largest_component


def _graph(pairs: list[tuple[int, int]], num_views: int, seed: int = 0) -> ViewGraph:
    rng = np.random.default_rng(seed)
    graph = ViewGraph(views={v: View(v, f"{v:04d}.jpg", 1) for v in range(1, num_views + 1)})
    for i, j in pairs:
        matches = np.stack([rng.permutation(50)[:40], rng.permutation(60)[:40]], axis=1)
        t = rng.normal(size=3)
        graph.edges.append(Edge(i, j, so3.random_rotations(1, rng)[0], t / np.linalg.norm(t), matches,
                                pose_source="stored", config="CALIBRATED"))
    return graph


def test_largest_component_filters_the_rest_and_reports_views():
    # component {1,2,3} (3 views) vs {4,5} (2 views); view 6 has no edge
    graph = _graph([(1, 2), (2, 3), (1, 3), (4, 5)], num_views=6)
    keep = largest_component(graph)
    assert keep == [1, 2, 3]
    assert graph.unregistered_views == [4, 5, 6]
    assert [e.status for e in graph.edges] == ["active", "active", "active", "filtered"]
    assert graph.edges[3].reason == "outside largest component"
    assert graph.counts()["filtered_by_reason"] == {"outside largest component": 1}


def test_tie_goes_to_the_component_with_the_smallest_view_id():
    graph = _graph([(3, 4), (1, 2)], num_views=4)
    assert largest_component(graph) == [1, 2]
    assert graph.unregistered_views == [3, 4]


def test_bridge_edges_are_the_ones_on_no_cycle():
    # a chain: every edge
    assert bridge_edges([(3, 7), (7, 10), (10, 11)]) == [True, True, True]
    # two triangles joined by one edge, and a leaf on the second
    pairs = [(0, 1), (1, 2), (2, 0), (2, 3), (3, 4), (4, 5), (5, 3), (5, 6)]
    assert bridge_edges(pairs) == [False, False, False, True, False, False, False, True]
    # the same pair twice is a cycle of two; a second component is searched too
    assert bridge_edges([(0, 1), (0, 1), (5, 6)]) == [False, False, True]
    # a long cycle with a chord: no bridge (the DFS is iterative, no recursion limit)
    ring = [(v, (v + 1) % 5000) for v in range(5000)] + [(0, 2500)]
    assert not any(bridge_edges(ring))
    assert bridge_edges([]) == []


def test_unchecked_edges_warn_for_the_chain_part_only():
    from rotonly_cli.stages.average import unchecked_edges, unchecked_edges_warning

    graph = _graph([(1, 2), (2, 3), (1, 3), (3, 4), (4, 5), (5, 6)], num_views=6)
    graph.edges[5].filter("too few inliers")  # 5-6 is not in the graph the run used
    assert unchecked_edges(graph, {1, 2, 3, 4, 5}) == [(3, 4), (4, 5)]
    assert unchecked_edges(graph, {1, 2, 3}) == []  # the triangle checks itself
    assert unchecked_edges(graph, {3, 4}) == []  # two views: nothing to check against
    warning = unchecked_edges_warning([(3, 4), (4, 5)])
    assert warning.startswith("2 pair(s) of the view graph lie on no cycle (edges 3-4, 4-5)")
    assert unchecked_edges_warning([]) is None


def test_first_filter_reason_wins_and_filtering_can_disconnect():
    graph = _graph([(1, 2), (2, 3)], num_views=3)
    graph.edges[1].filter("too few inliers")
    graph.edges[1].filter("rotation averaging outlier")
    assert graph.edges[1].reason == "too few inliers"
    assert largest_component(graph) == [1, 2]
    assert graph.unregistered_views == [3]
    assert graph.active_edges() == [0]


def test_view_graph_json_is_deterministic_and_has_every_edge(tmp_path):
    graph = _graph([(1, 2), (2, 3), (1, 3)], num_views=3)
    graph.edges[2].filter("too few inliers")
    graph.edges[0].residual_deg = float("nan")  # NaN must become null, not invalid JSON
    write_view_graph_json(tmp_path / "a.json", graph)
    write_view_graph_json(tmp_path / "b.json", graph)
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    document = json.loads((tmp_path / "a.json").read_text())
    assert [(e["i"], e["j"], e["status"], e["reason"]) for e in document["edges"]] == [
        (1, 2, "active", ""), (2, 3, "active", ""), (1, 3, "filtered", "too few inliers")]
    assert document["edges"][0]["residual_deg"] is None
    assert document["edges"][1]["num_inliers"] == 40
    np.testing.assert_allclose(document["edges"][1]["R_j_from_i"], graph.edges[1].R_j_from_i, rtol=0, atol=0)


def test_workspace_state_round_trip(tmp_path):
    graph = _graph([(1, 2), (2, 3), (1, 3)], num_views=3)
    graph.edges[1].scene_kind = "PURE_ROTATION"
    graph.edges[1].detection_value = 0.25
    graph.edges[2].filter("rotation averaging outlier")
    rotations = so3.random_rotations(3, np.random.default_rng(5))
    rotations[2] = np.nan
    state = WorkspaceState("in/database.db", "colmap-db", None, "imgs", graph, rotations, None,
                           ["load", "identify"], {"grrm": True})
    save_state(tmp_path, state)
    back = load_state(tmp_path)
    assert (back.input_path, back.input_kind, back.image_path, back.stages) == (
        "in/database.db", "colmap-db", "imgs", ["load", "identify"])
    assert back.centers is None
    np.testing.assert_array_equal(back.rotations, rotations)
    assert [(e.i, e.j, e.status, e.reason, e.scene_kind) for e in back.graph.edges] == [
        (e.i, e.j, e.status, e.reason, e.scene_kind) for e in graph.edges]
    assert back.graph.edges[1].detection_value == 0.25 and np.isnan(back.graph.edges[0].detection_value)
    for a, b in zip(back.graph.edges, graph.edges):
        np.testing.assert_array_equal(a.matches, b.matches)
        np.testing.assert_array_equal(a.R_j_from_i, b.R_j_from_i)
    assert back.graph.views[2].name == "0002.jpg"


def test_load_state_of_a_plain_folder_is_input_error(tmp_path):
    with pytest.raises(InputError, match="not a rotonly workspace"):
        load_state(tmp_path)


def test_copy_shares_match_arrays_and_stays_as_it_was():
    graph = _graph([(1, 2), (2, 3)], num_views=3)
    before = [e.matches.copy() for e in graph.edges]
    copied = graph.copy()
    assert all(c.matches is e.matches for c, e in zip(copied.edges, graph.edges))  # no 16 B per match copied
    assert copied.edges[0] is not graph.edges[0] and copied.edges[0].R_j_from_i is not graph.edges[0].R_j_from_i
    graph.edges[0].drop_matches(np.arange(40) % 2 == 0, "test")
    graph.edges[1].filter("test")
    assert graph.edges[0].num_inliers == 20 and copied.edges[0].num_inliers == 40
    assert all(np.array_equal(c.matches, m) for c, m in zip(copied.edges, before))
    assert copied.edges[0].dropped_matches == {} and copied.edges[1].active
