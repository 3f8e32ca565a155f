"""The pairs' scatter about the final rotations (stages.average.pair_residuals_deg): what it
measures, which edges it takes, and the run's warning when it is large."""

import numpy as np
import pytest

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.alignment import rotation_errors_after_alignment
from rotonly_cli.scene.types import Pose, View
from rotonly_cli.scene.view_graph import Edge, ViewGraph
from rotonly_cli.stages.average import PAIR_SCATTER_WARN_DEG, pair_residuals_deg, pair_scatter_deg, pair_scatter_warning


def _graph(R: np.ndarray) -> ViewGraph:
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 0) for v in range(len(R))})
    matches = np.zeros((40, 2), dtype=np.int64)
    for i, j, kind in ((0, 1, "REGULAR"), (1, 2, "REGULAR"), (0, 2, "REGULAR"), (2, 3, "PURE_ROTATION"),
                       (1, 3, "REGULAR"), (0, 4, "REGULAR")):
        graph.edges.append(Edge(i, j, R[j] @ R[i].T, np.zeros(3), matches, scene_kind=kind))
    return graph


def test_pair_residuals_are_the_angles_to_the_final_rotations_of_the_regular_edges_between_posed_views():
    rng = np.random.default_rng(3)
    R = np.stack([so3.exp(rng.normal(scale=0.5, size=3)) for _ in range(5)])
    graph = _graph(R)
    tilt = so3.exp(np.radians(0.3) * np.array([0.6, 0.0, 0.8]))
    graph.edges[2].R_j_from_i = tilt @ graph.edges[2].R_j_from_i  # (0, 2): 0.3 deg off
    graph.edges[3].R_j_from_i = so3.exp([0.1, 0, 0]) @ graph.edges[3].R_j_from_i  # PURE_ROTATION: left out
    graph.edges[4].R_j_from_i = so3.exp([0.2, 0, 0]) @ graph.edges[4].R_j_from_i
    graph.edges[4].filter("too few inliers")  # filtered: left out
    posed = {v: R[v] for v in range(4)}  # view 4 has no pose: (0, 4) left out
    residuals = pair_residuals_deg(graph, posed)
    np.testing.assert_allclose(residuals, [0.0, 0.0, 0.3], atol=1e-9)
    poses = {v: Pose(R[v], np.zeros(3)) for v in range(4)}
    assert pair_scatter_deg(graph, poses) == pytest.approx(0.0, abs=1e-9)
    assert pair_scatter_deg(graph, {0: poses[0]}) is None  # no REGULAR edge between posed views


def test_the_scatter_warning_starts_above_its_threshold():
    assert pair_scatter_warning(None) is None
    assert pair_scatter_warning(PAIR_SCATTER_WARN_DEG) is None
    warning = pair_scatter_warning(0.164)
    assert warning.startswith("the pairs' own relative rotations scatter by a median 0.16 deg")
    assert "bundle adjustment" in warning and "pair_residual_deg_median" in warning


def test_a_noisy_sparse_capture_warns_and_its_rotation_error_is_of_the_order_of_the_scatter():
    """Eight simulated views around a scene: 400 points at 0.5 px give no warning; 150 points at
    4 px scatter the pairs by more than the threshold, the run warns, and the rotation error
    against the truth is of that order (0.2-2x the median)."""
    import rotonly_cli
    from rotonly_cli.simulation.layout_scenes import simulate_multiview

    for noise_px, points, warns in ((0.5, 400, False), (4.0, 150, True)):
        simulated = simulate_multiview("circular", num_views=8, num_points=points, noise_px=noise_px, rng=1, window=3)
        result = rotonly_cli.run(simulated.scene, jobs=1)
        scatter = result.summary["pair_residual_deg_median"]
        scatter_warnings = [w for w in result.summary["warnings"] if w.startswith("the pairs' own relative")]
        assert (scatter > PAIR_SCATTER_WARN_DEG) is warns and len(scatter_warnings) == int(warns)
        views = sorted(result.rotations)
        error = rotation_errors_after_alignment(np.stack([result.rotations[v] for v in views]),
                                                np.stack([simulated.gt_poses[v].R_cam_from_world
                                                          for v in views]))[0].mean()
        if warns:
            assert 0.2 * scatter < error < 2.0 * scatter
        else:
            assert scatter < PAIR_SCATTER_WARN_DEG / 2 and error < 0.01
