"""Stage reject: matches off the epipolar geometry of the global poses are dropped, edges left
with too few are filtered, clean matches stay."""

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.options import RejectOptions
from rotonly_cli.scene.types import Pose, View
from rotonly_cli.scene.view_graph import Edge, ViewGraph
from rotonly_cli.stages.reject import DROP_REASON, reject_round

FOCAL = 1000.0


def _graph(rng, wrong_px: float, num_wrong: int):
    R = np.stack([so3.exp(rng.normal(scale=0.1, size=3)) for _ in range(3)])
    C = np.array([[0.0, 0, 0], [1.0, 0.1, 0], [2.0, -0.1, 0.2]])
    X = rng.uniform([-3, -3, 8], [3, 3, 12], size=(200, 3))
    cam = np.einsum("vij,vnj->vni", R, X[None] - C[:, None])
    x = cam[..., :2] / cam[..., 2:3] + rng.normal(scale=0.3 / FOCAL, size=(3, 200, 2))
    normalized = {v: x[v].copy() for v in range(3)}
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 0) for v in range(3)})
    for i, j in ((0, 1), (1, 2), (0, 2)):
        matches = np.stack([np.arange(200), np.arange(200)], axis=1)
        graph.edges.append(Edge(i, j, R[j] @ R[i].T, np.zeros(3), matches, scene_kind="REGULAR"))
    # wrong matches in edge (0, 1): new keypoints in view 1, off by wrong_px in a random direction
    wrong = rng.normal(size=(num_wrong, 2))
    normalized[1] = np.concatenate([normalized[1], x[1, :num_wrong] + wrong / np.linalg.norm(wrong, axis=1,
                                                                                             keepdims=True)
                                    * wrong_px / FOCAL])
    graph.edges[0].matches[:num_wrong, 1] = 200 + np.arange(num_wrong)
    return graph, normalized, R, C


def test_wrong_matches_dropped_clean_ones_kept():
    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=20)
    report = reject_round(graph, normalized, R, C, np.full(3, FOCAL), RejectOptions(), min_inliers=30)
    first = graph.edges[0]
    # most of the 20 wrong ones go (those whose offset lies along their epipolar line may stay)
    assert 12 <= first.dropped_matches[DROP_REASON] <= 20
    assert report["num_dropped"] == sum(e.dropped_matches.get(DROP_REASON, 0) for e in graph.edges)
    assert graph.edges[1].dropped_matches.get(DROP_REASON, 0) <= 2  # 0.3 px noise, 5-sigma threshold
    assert report["threshold_px"] == 5 * report["sigma_px"] and 0.2 < report["sigma_px"] < 0.45  # 0.3 px noise
    assert all(e.active for e in graph.edges)


def test_edge_that_would_be_emptied_keeps_its_matches():
    """Filtering it could cut a weakly connected view loose; it is reported instead."""
    graph, normalized, R, C = _graph(np.random.default_rng(1), wrong_px=30.0, num_wrong=190)
    report = reject_round(graph, normalized, R, C, np.full(3, FOCAL), RejectOptions(), min_inliers=30)
    assert graph.edges[0].active and graph.edges[0].num_inliers == 200 and not graph.edges[0].dropped_matches
    assert report["edges_kept_whole"] == 1
    assert graph.edges[1].active and graph.edges[2].active


def _run_for_reject_stage(graph, normalized, R, C):
    from rotonly_cli.chain import Run
    from rotonly_cli.options import RunOptions
    from rotonly_cli.scene.types import Intrinsics, SfMScene

    scene = SfMScene(views=dict(graph.views), normalized=normalized,
                     intrinsics={0: Intrinsics(0, "SIMPLE_PINHOLE", 2000, 2000, np.array([FOCAL, 1000.0, 1000.0]))})
    run = Run("simulated", "simulation", scene, graph, RunOptions(), rotations=R, centers=C)
    run.reports["translate"] = {"baselines": {"views_off": {}}, "solve": "first"}
    return run


def _fake_solves(monkeypatch, views_off: dict, views_without_centre: tuple = ()):
    """optimize: rotations unchanged (a copy); translate: centres moved, the baseline check
    reporting ``views_off``, LiGT leaving ``views_without_centre`` without a centre."""
    from rotonly_cli import chain

    def optimize(run):
        run.rotations = run.rotations.copy()

    def translate(run):
        run.centers = run.centers * 0.01
        run.reports["translate"] = {"baselines": {"views_off": dict(views_off)}, "solve": "after the round",
                                    "views_without_centre": list(views_without_centre)}

    monkeypatch.setattr(chain, "optimize_stage", optimize)
    monkeypatch.setattr(chain, "translate_stage", translate)


def test_round_whose_ligt_solve_collapses_is_undone(monkeypatch):
    """A round after which the centres of some view contradict its pairs' baselines (none did
    before) is undone: matches, rotations, centres and reports as they were."""
    from rotonly_cli.chain import reject_stage

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=60)
    run = _run_for_reject_stage(graph, normalized, R, C)
    _fake_solves(monkeypatch, {"1": 40.0})
    reject_stage(run)
    first_round = run.reports["reject"]["rounds"][0]
    assert first_round["num_dropped"] >= 30
    assert first_round["undone"] == {"views_off": ["1"], "views_without_centre": []}
    assert len(run.reports["reject"]["rounds"]) == 1 and run.reports["reject"]["num_dropped"] == 0
    assert run.graph.edges[0].num_inliers == 200 and not run.graph.edges[0].dropped_matches
    assert run.rotations is R and run.centers is C and run.reports["translate"]["solve"] == "first"


def test_round_that_leaves_views_without_a_centre_is_undone(monkeypatch):
    """A round whose dropped matches cut views out of the set LiGT's tracks tie together
    (castle-P19, OpenMVG matches, seed 1: views 12-15) is undone: a registered view is worth
    more than the matches the round would drop."""
    from rotonly_cli.chain import reject_stage

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=60)
    run = _run_for_reject_stage(graph, normalized, R, C)
    _fake_solves(monkeypatch, {}, views_without_centre=(2,))
    reject_stage(run)
    rounds = run.reports["reject"]["rounds"]
    assert len(rounds) == 1 and rounds[0]["undone"] == {"views_off": [], "views_without_centre": [2]}
    assert run.reports["reject"]["num_dropped"] == 0 and run.graph.edges[0].num_inliers == 200
    assert run.rotations is R and run.centers is C and run.reports["translate"]["solve"] == "first"


def test_round_whose_solve_stays_sound_is_kept(monkeypatch):
    from rotonly_cli.chain import reject_stage

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=60)
    run = _run_for_reject_stage(graph, normalized, R, C)
    _fake_solves(monkeypatch, {})
    reject_stage(run)
    assert "undone" not in run.reports["reject"]["rounds"][0]
    assert run.graph.edges[0].num_inliers <= 170 and run.reports["translate"]["solve"] == "after the round"
    assert np.allclose(run.centers, 0.01 * C)


def test_round_dropping_fewer_matches_than_an_edge_needs_is_not_applied(monkeypatch):
    """12-20 wrong matches of 600: too few to move the rotations, so no GRRM + LiGT re-solve
    (and the matches stay, so that the rotations are those of the matches written)."""
    from rotonly_cli.chain import reject_stage

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=20)
    run = _run_for_reject_stage(graph, normalized, R, C)
    _fake_solves(monkeypatch, {})
    reject_stage(run)
    (only_round,) = run.reports["reject"]["rounds"]
    assert 12 <= only_round["num_dropped"] < 30 and only_round["not_applied"] == "fewer than 30 matches"
    assert run.reports["reject"]["num_dropped"] == 0
    assert run.graph.edges[0].num_inliers == 200 and not run.graph.edges[0].dropped_matches
    assert run.centers is C and run.reports["translate"]["solve"] == "first"  # no re-solve


def test_stage_times_add_up_over_the_re_solves(monkeypatch):
    """optimize.json and translate.json carry the time of every solve and their number; the
    reject stage's own time leaves the re-solves out (the report's stage times add up)."""
    from rotonly_cli import chain
    from rotonly_cli.chain import reject_stage

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=60)
    run = _run_for_reject_stage(graph, normalized, R, C)
    run.reports["optimize"] = {"time_s": 1.0}
    run.reports["translate"]["time_s"] = 1.5

    def optimize(run):
        run.rotations = run.rotations.copy()
        run.reports["optimize"] = {"time_s": 2.0, "solve": "after the round"}

    def translate(run):
        run.reports["translate"] = {"baselines": {"views_off": {}}, "time_s": 3.0, "solve": "after the round"}

    monkeypatch.setattr(chain, "optimize_stage", optimize)
    monkeypatch.setattr(chain, "translate_stage", translate)
    reject_stage(run)
    assert len(run.reports["reject"]["rounds"]) == 2  # the second round finds nothing more
    assert run.reports["optimize"] == {"time_s": 3.0, "solve": "after the round", "solves": 2}
    assert run.reports["translate"]["time_s"] == 4.5 and run.reports["translate"]["solves"] == 2
    assert 0.0 <= run.reports["reject"]["time_s"] < 1.0


def test_undone_round_warning_names_the_views_and_the_matches():
    from rotonly_cli.stages.reject import undone_round_warning

    assert undone_round_warning(None) is None
    assert undone_round_warning({"rounds": [{"num_dropped": 40}]}) is None
    lost = undone_round_warning({"rounds": [{"num_dropped": 226}, {"num_dropped": 338, "undone": {
        "views_off": [], "views_without_centre": [12, 13, 14, 15]}}]})
    assert "view(s) 12, 13, 14, 15 " in lost and "the 338 matches" in lost and "could not place them" in lost
    off = undone_round_warning({"rounds": [{"num_dropped": 60, "undone": {"views_off": ["1"],
                                                                           "views_without_centre": []}}]})
    assert "view(s) 1 " in off and "off their pairs' baselines" in off


def test_run_summary_carries_the_undone_round_warning(monkeypatch):
    """The round undone for a lost centre ends up among the run's warnings (stderr, run.json)."""
    from rotonly_cli.chain import reject_stage
    from rotonly_cli.pipeline import summarize_outcome

    graph, normalized, R, C = _graph(np.random.default_rng(0), wrong_px=15.0, num_wrong=60)
    run = _run_for_reject_stage(graph, normalized, R, C)
    _fake_solves(monkeypatch, {}, views_without_centre=(2,))
    reject_stage(run)

    class Scene:
        poses = {v: Pose(R[v], C[v]) for v in range(3)}

    summary: dict = {}
    summarize_outcome(run, Scene(), summary)
    assert any(w.startswith("view(s) 2 are tied to the rest by few tracks") for w in summary["warnings"])
