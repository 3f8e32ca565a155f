"""stages/load: the stable consensus of seeded RANSAC runs per edge, with the extra runs spent
only on edges whose first run found enough inliers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io.colmap import read_database
from rotonly_cli.options import LoadOptions
from rotonly_cli.stages import load
from tests.helpers import DATA_FIXTURES


@pytest.fixture(scope="module")
def scene():
    return read_database(DATA_FIXTURES / "herzjesu_p8" / "database.db")


def test_weak_edges_skip_the_extra_runs_and_the_graph_is_that_of_every_run(scene, monkeypatch):
    """An edge whose first RANSAC run has fewer inliers than --min-inliers is filtered whatever
    the other runs find (the stable set is a subset of every run's inliers): those runs are
    skipped, and every edge ends exactly as when all runs are made."""
    # a third of the fixture's edges fall short (matches capped at 1000); every strong edge makes every run
    options = LoadOptions(min_inliers=500, consensus_agreement=None)
    calls: list[int] = []
    ransac = load._relative_pose_ransac

    def counted(x_i, x_j, focal_i, focal_j, max_error_px, seed, options_, inlier_ratio=None):
        calls.append(seed)
        return ransac(x_i, x_j, focal_i, focal_j, max_error_px, seed, options_, inlier_ratio)

    monkeypatch.setattr(load, "_relative_pose_ransac", counted)
    graph, report = load.build_view_graph(scene, options)
    monkeypatch.undo()
    threshold = report["ransac_max_error_px"]

    strong = weak = 0
    for edge in graph.edges:
        matches = np.asarray(scene.pairs[(edge.i, edge.j)].matches, dtype=np.int64).reshape(-1, 2)
        if len(matches) < options.min_inliers:
            continue  # filtered before any RANSAC
        x_i, x_j = scene.normalized[edge.i][matches[:, 0]], scene.normalized[edge.j][matches[:, 1]]
        focal_i = scene.intrinsics[scene.views[edge.i].intrinsics_id].focal_px
        focal_j = scene.intrinsics[scene.views[edge.j].intrinsics_id].focal_px
        runs = [ransac(x_i, x_j, focal_i, focal_j, threshold, options.seed, options)]
        runs += [ransac(x_i, x_j, focal_i, focal_j, threshold, options.seed + r, options, runs[0][2].mean())
                 for r in range(1, options.consensus_runs)]
        R, _, stable = load.stable_consensus(runs)
        if runs[0][2].sum() < options.min_inliers:
            weak += 1
            assert edge.status != "active" and edge.reason == "too few inliers"
        elif stable.sum() >= options.min_inliers:
            strong += 1
            assert edge.status == "active"
            np.testing.assert_array_equal(edge.R_j_from_i, R)
            np.testing.assert_array_equal(edge.matches, matches[stable])
        else:
            assert edge.status != "active"
    assert strong >= 3 and weak >= 2, (strong, weak)
    extra_runs = sum(seed != options.seed for seed in calls)
    assert extra_runs == (options.consensus_runs - 1) * (report["num_reestimated"] - weak)


def test_ransac_stops_at_the_trials_min_inliers_needs(monkeypatch):
    """A pair of 40 matches can only keep an edge with 30 inliers (ratio 0.75): its RANSAC gets
    the trials that ratio needs, not --ransac-max-trials; a pair of 5000 matches gets the cap."""
    import pycolmap

    given = []
    real = pycolmap.RANSACOptions

    def recording(**kwargs):
        given.append(kwargs["max_num_trials"])
        return real(**kwargs)

    monkeypatch.setattr(pycolmap, "RANSACOptions", recording)
    rng = np.random.default_rng(0)
    options = LoadOptions(min_inliers=30)
    for n in (40, 5000):
        x = rng.normal(size=(n, 2))
        load._relative_pose_ransac(x, x + rng.normal(scale=0.01, size=(n, 2)), 1000.0, 1000.0, 1.0, 0, options)
    from rotonly_cli.geometry import pairwise as pg

    assert given[0] == pg.ransac_trials_needed(30 / 40, 5, options.ransac_confidence) == 34
    assert given[1] == options.ransac_max_trials


def _fisheye_scene():
    """Two views of an OPENCV_FISHEYE camera (f = 420 px on 1536 x 1024: wider than 180°),
    keypoints along the image's horizontal axis at 30°, 80°, 100° and 120° off the optical axis
    (equidistant: r = f θ), matched to each other."""
    from rotonly_cli.io.cameras import normalize
    from rotonly_cli.scene.types import Intrinsics, PairMatches, SfMScene, View

    camera = Intrinsics(1, "OPENCV_FISHEYE", 1536, 1024, np.array([420.0, 420.0, 768.0, 512.0, 0.0, 0.0, 0.0, 0.0]))
    angles = np.deg2rad([30.0, 80.0, 100.0, 120.0])
    pixels = np.column_stack([768.0 + 420.0 * angles, np.full(4, 512.0)])
    scene = SfMScene(source="test")
    scene.intrinsics[1] = camera
    for v in (1, 2):
        scene.views[v] = View(v, f"{v}.jpg", 1, width=1536, height=1024)
        scene.keypoints[v] = pixels.copy()
        scene.normalized[v] = normalize(camera, pixels)
    scene.pairs[(1, 2)] = PairMatches(1, 2, np.array([[0, 0], [1, 1], [2, 2], [3, 1], [1, 3]]))
    return scene


def test_keypoints_a_fisheye_cannot_undistort_are_found():
    from rotonly_cli.io.cameras import undistortion_failures

    scene = _fisheye_scene()
    failed = undistortion_failures(scene.intrinsics[1], scene.keypoints[1], scene.normalized[1])
    np.testing.assert_array_equal(failed, [False, False, True, True])  # 90° or more off the axis
    np.testing.assert_allclose(scene.normalized[1][:2, 0], np.tan(np.deg2rad([30.0, 80.0])), rtol=1e-6)


def test_the_matches_of_keypoints_the_camera_cannot_undistort_are_left_out_and_warned():
    from rotonly_cli.stages.load import unprojectable_warning, without_unprojectable_keypoints

    scene = _fisheye_scene()
    before = scene.pairs[(1, 2)].matches.copy()
    cleaned, report = without_unprojectable_keypoints(scene)
    np.testing.assert_array_equal(cleaned.pairs[(1, 2)].matches, [[0, 0], [1, 1]])
    assert np.isnan(cleaned.normalized[1][2:]).all() and np.isfinite(cleaned.normalized[1][:2]).all()
    assert report == {"keypoints_not_undistorted": {"1": 2, "2": 2}, "matches_of_them_left_out": 3}
    assert "4 keypoints in 2 view(s)" in unprojectable_warning(report)
    # the input scene is not changed
    np.testing.assert_array_equal(scene.pairs[(1, 2)].matches, before)
    assert np.isfinite(scene.normalized[1]).all()
    # a camera that can undistort every keypoint: the same scene, no report, no warning
    herzjesu = read_database(DATA_FIXTURES / "herzjesu_p8" / "database.db")
    same, nothing = without_unprojectable_keypoints(herzjesu)
    assert same is herzjesu and nothing == {} and unprojectable_warning(nothing) is None


def _simulated_pair(num_inliers: int, num_outliers: int, seed: int = 0):
    """Two views of a PINHOLE camera (f = 800 px, 960 x 960) 1 unit apart looking at points 5-9
    units away, 0.3 px of noise; ``num_outliers`` matches of random keypoints after the inliers."""
    from rotonly_cli.io.cameras import normalize
    from rotonly_cli.scene.types import Intrinsics, PairMatches, SfMScene, View

    rng = np.random.default_rng(seed)
    camera = Intrinsics(1, "PINHOLE", 960, 960, np.array([800.0, 800.0, 480.0, 480.0]))
    points = np.column_stack([rng.uniform(-2.5, 2.5, (num_inliers, 2)), rng.uniform(5.0, 9.0, num_inliers)])
    angle = np.deg2rad(8.0)
    R = np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
    in_j = points @ R.T + np.array([-1.0, 0.0, 0.0])
    scene = SfMScene(source="test")
    scene.intrinsics[1] = camera
    for v, xyz in ((1, points), (2, in_j)):
        pixels = 800.0 * xyz[:, :2] / xyz[:, 2:] + 480.0 + rng.normal(scale=0.3, size=(num_inliers, 2))
        pixels = np.vstack([pixels, rng.uniform(0.0, 960.0, (num_outliers, 2))])
        scene.views[v] = View(v, f"{v}.jpg", 1, width=960, height=960)
        scene.keypoints[v] = pixels
        scene.normalized[v] = normalize(camera, pixels)
    scene.pairs[(1, 2)] = PairMatches(1, 2, np.repeat(np.arange(num_inliers + num_outliers)[:, None], 2, axis=1))
    return scene


def test_the_consensus_runs_make_the_trials_the_first_runs_inlier_ratio_needs(monkeypatch):
    """A pair of 1200 matches, 25 % of them random: the first run has the 20-trial floor and
    the min_inliers bound (30 / 1200: the 2000 cap); it finds the inlier ratio (0.75). By
    default every consensus run has the first run's trials (the bound by the ratio changed
    castle-P19's refuted pairs); the bound a known ratio gives (the fast front end's) stops at
    the trials that ratio needs at 0.9999 (34), above the floor."""
    import pycolmap

    from rotonly_cli.geometry import pairwise as pg

    given = []
    real = pycolmap.RANSACOptions

    def recording(**kwargs):
        given.append((kwargs["min_num_trials"], kwargs["max_num_trials"]))
        return real(**kwargs)

    scene = _simulated_pair(900, 300)
    options = LoadOptions(ransac_max_error_px=1.0, consensus_agreement=None, jobs=1)
    monkeypatch.setattr(pycolmap, "RANSACOptions", recording)
    graph, report = load.build_view_graph(scene, options)
    assert report["ransac_runs"] == options.consensus_runs == len(given)
    assert set(given) == {(20, 2000)}
    ratio = (graph.edges[0].num_inliers + graph.edges[0].dropped_matches.get("unstable consensus", 0)) / 1200
    assert 0.74 <= ratio <= 0.76  # the 900 inliers, as the first run and every run found them
    # 0.75 needs 34 trials; a run's ratio is the 900 within a few matches (35 at 0.745)
    fewest, most = (pg.ransac_trials_needed(r, 5, options.ransac_confidence) for r in (0.76, 0.74))
    assert (fewest, most) == (32, 37)
    assert fewest <= load.ransac_trials(1200, options, ratio)[1] <= most
    assert load.ransac_trials(1200, options, 0.99) == (20, 20)  # 4 needed: the floor stays
    assert load.ransac_trials(1200, options, 0.3) == (20, 2000)  # 4549 needed: the cap


def test_runs_that_agree_are_not_repeated_and_runs_that_differ_are():
    """consensus_agreement: a clean pair's first two runs keep the same matches, so it makes
    two runs, not four, and keeps the matches both accept. Masks that differ in more than the agreement do not agree."""
    scene = _simulated_pair(1500, 0)
    graph, report = load.build_view_graph(scene, LoadOptions(ransac_max_error_px=1.0, jobs=1,
                                                             consensus_agreement=0.01, agreement_min_edges=0))
    assert report["ransac_runs"] == 2
    assert graph.edges[0].num_inliers >= 1450
    every, _ = load.build_view_graph(scene, LoadOptions(ransac_max_error_px=1.0, jobs=1, consensus_agreement=None))
    assert every.edges[0].num_inliers <= graph.edges[0].num_inliers  # four runs' common matches are fewer

    def run(mask):
        return np.eye(3), np.zeros(3), np.asarray(mask, dtype=bool)

    mask = np.ones(200, dtype=bool)
    one_off, three_off = mask.copy(), mask.copy()
    one_off[0] = False
    three_off[:3] = False
    assert load.runs_agree([run(mask), run(one_off)], 0.01)  # 1 of 200 differs
    assert not load.runs_agree([run(mask), run(three_off)], 0.01)  # 3 of 200
    assert load.runs_agree([run(mask), run(three_off)], 0.02)


def test_only_edges_of_many_matches_take_the_two_agreeing_runs():
    """With consensus_agreement the agreeing runs are the front end of the edges above
    agreement_min_matches (1000); a smaller edge makes its four runs on every match, exactly as
    without it."""
    options = LoadOptions(ransac_max_error_px=1.0, jobs=1, consensus_agreement=0.01, agreement_min_edges=0)
    assert options.agreement_min_matches == 1000
    large, small = _simulated_pair(1500, 0), _simulated_pair(800, 0)
    assert load.build_view_graph(large, options)[1]["ransac_runs"] == 2
    graph, report = load.build_view_graph(small, options)
    assert report["ransac_runs"] == 4
    every, _ = load.build_view_graph(small, replace(options, consensus_agreement=None))
    assert np.array_equal(graph.edges[0].matches, every.edges[0].matches)
    assert np.array_equal(graph.edges[0].R_j_from_i, every.edges[0].R_j_from_i)


def test_auto_takes_the_agreeing_runs_from_agreement_min_edges_edges_on():
    """--consensus auto (the default): the agreeing runs only in a load of at least
    agreement_min_edges edges to re-estimate; below, every edge makes its four runs and keeps
    what full keeps, bit for bit; the report says which front end ran."""
    options = LoadOptions(ransac_max_error_px=1.0, jobs=1)
    assert options.consensus_agreement == 0.01 and options.agreement_min_edges == 1000
    large = _simulated_pair(1500, 0)  # one edge of 1500 matches
    graph, report = load.build_view_graph(large, options)
    assert report["ransac_runs"] == 4 and report["agreeing_runs"] is False
    full, full_report = load.build_view_graph(large, replace(options, consensus_agreement=None))
    assert full_report["agreeing_runs"] is False
    assert np.array_equal(graph.edges[0].matches, full.edges[0].matches)
    assert np.array_equal(graph.edges[0].R_j_from_i, full.edges[0].R_j_from_i)
    _, report = load.build_view_graph(large, replace(options, agreement_min_edges=1))
    assert report["ransac_runs"] == 2 and report["agreeing_runs"] is True
    with pytest.raises(InputError, match="must be >= 0") as raised:
        LoadOptions(agreement_min_edges=-1).validate()
    assert raised.value.field == "agreement_min_edges"


def test_a_negative_agreement_min_matches_is_refused():
    from rotonly_cli.errors import InputError

    with pytest.raises(InputError, match="must be >= 0") as raised:
        LoadOptions(agreement_min_matches=-1).validate()
    assert raised.value.field == "agreement_min_matches"
    assert LoadOptions(agreement_min_matches=0).validate().agreement_min_matches == 0
