"""The triangulate stage splits tracks merged by wrong matches (geometry/track_split.py)
instead of dropping them: a simulated capture with 5 % of the matches moved along their
epipolar lines (they pass every two-view test), at the true poses."""

from __future__ import annotations

import numpy as np
import pytest

from rotonly_cli.scene.view_graph import Edge, ViewGraph
from rotonly_cli.simulation.layout_scenes import simulate_multiview
from rotonly_cli.stages.triangulate import triangulated_tracks


def simulated_capture():
    problem = simulate_multiview("circular", num_views=16, num_points=1500, noise_px=0.5, rng=3, window=4,
                                 init="truth", epipolar_outlier_fraction=0.05)
    scene = problem.scene
    graph = ViewGraph(views=dict(scene.views))
    for (i, j), pair in sorted(scene.pairs.items()):
        graph.edges.append(Edge(i, j, pair.R_j_from_i, pair.t_j_from_i, pair.matches))
    ids = graph.view_ids()
    R = np.stack([problem.gt_poses[v].R_cam_from_world for v in ids])
    C = np.stack([problem.gt_poses[v].center for v in ids])
    # (view row, keypoint) -> simulated point: keypoint k of view v is the k-th point it sees;
    # the wrong keypoints come after those and belong to no point
    truth = {}
    for row, v in enumerate(ids):
        for k, point in enumerate(np.flatnonzero(problem.visibility[v])):
            truth[(row, k)] = point
    return problem, graph, R, C, truth


@pytest.fixture(scope="module")
def capture():
    return simulated_capture()


def _pure(kept, truth) -> np.ndarray:
    """Per track: all its observations are of one simulated point."""
    point = np.array([truth.get((v, f), -1) for v, f in zip(kept.view.tolist(), kept.feature.tolist())])
    first = point[kept.offsets[:-1]]
    pure = first >= 0
    np.logical_and.at(pure, kept.track_id, point == first[kept.track_id])
    return pure


def test_tracks_merged_by_wrong_matches_are_split_not_dropped(capture):
    problem, graph, R, C, truth = capture
    dropped = triangulated_tracks(graph, problem.scene, R, C, split=False)
    split = triangulated_tracks(graph, problem.scene, R, C)
    # measured: 1500 simulated points; without the split 304 points (298 of one simulated
    # point each: a wrong keypoint passed the reprojection test in 6) -- the 1198 components
    # a wrong match hung a second keypoint of a view on are dropped; with it 1502, 1496 pure
    assert dropped.kept.num_tracks == 304 and dropped.kept.num_inconsistent == 1198
    assert _pure(dropped.kept, truth).sum() == 298
    assert split.split["num_conflicting_components"] == 1198 and split.split["num_parts"] == 1198
    assert split.kept.num_tracks == 1502 and _pure(split.kept, truth).sum() == 1496
    # every track of the old result is still there, with the same observations
    assert split.kept.track_id[:dropped.kept.num_observations].max() == dropped.kept.num_tracks - 1
    np.testing.assert_array_equal(split.kept.feature[:dropped.kept.num_observations], dropped.kept.feature)
    # the points are the simulated ones
    points = problem.points_in_world[[truth[(v, f)] for v, f in
                                      zip(split.kept.view[split.kept.offsets[:-1]].tolist(),
                                          split.kept.feature[split.kept.offsets[:-1]].tolist())]]
    error = np.linalg.norm(split.points - points, axis=1)  # m; the points lie 0-400 m above the cameras
    assert np.median(error) < 0.15 and np.percentile(error, 90) < 0.45
