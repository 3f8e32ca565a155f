"""Tracks merged through a wrong match, split into their consistent parts (geometry/track_split.py)."""

from __future__ import annotations

import itertools

import numpy as np

from rotonly_cli.geometry import so3
from rotonly_cli.geometry.track_split import split_conflicts
from rotonly_cli.geometry.tracks import build_tracks, gather_observations
from rotonly_cli.geometry.triangulation import triangulate_tracks

FOCAL = 1000.0
THRESHOLD = 2.0 / FOCAL  # 2 px


def _cameras(num_views: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Cameras 1 m apart along x, looking along +z with small tilts."""
    R = so3.random_rotations(num_views, np.random.default_rng(5), max_angle=np.radians(3.0))
    C = np.stack([np.arange(num_views, dtype=float), np.zeros(num_views), np.zeros(num_views)], axis=1)
    return R, C


def _project(R, C, X):
    camera = np.einsum("vij,vj->vi", R, X - C)
    return camera[:, :2] / camera[:, 2:3]


def _all_pairs(feature_of_view: dict[int, int]) -> list[tuple[int, int, int, int]]:
    """(view i, feature, view j, feature) for every pair of views of one point."""
    views = sorted(feature_of_view)
    return [(i, feature_of_view[i], j, feature_of_view[j]) for i, j in itertools.combinations(views, 2)]


def _pairs(links):
    """build_tracks' (pair keys, matches) from (i, fi, j, fj) links."""
    grouped: dict[tuple[int, int], list] = {}
    for i, fi, j, fj in links:
        grouped.setdefault((i, j), []).append((fi, fj))
    keys = sorted(grouped)
    return keys, [np.array(grouped[k]) for k in keys]


def _split(R, C, keypoints, links):
    tracks = build_tracks(*_pairs(links), keep_conflicts=True)
    xy = gather_observations(tracks.conflicts, keypoints)
    result = split_conflicts(R, C, tracks.conflicts, xy, np.full(len(xy), THRESHOLD))
    return tracks, xy, result


def _parts(conflicts, part):
    return sorted(sorted(zip(conflicts.view[part == p].tolist(), conflicts.feature[part == p].tolist()))
                  for p in range(int(part.max()) + 1))


def test_two_tracks_merged_by_a_wrong_match_are_split_and_both_triangulated():
    R, C = _cameras()
    P, Q = np.array([1.0, 0.5, 10.0]), np.array([3.5, -1.0, 12.0])
    keypoints = [np.stack([_project(R, C, P)[v], _project(R, C, Q)[v]]) for v in range(6)]  # feature 0: P, 1: Q
    links = _all_pairs(dict.fromkeys(range(6), 0)) + _all_pairs(dict.fromkeys(range(6), 1)) + [(0, 0, 3, 1)]
    tracks, xy, result = _split(R, C, keypoints, links)
    assert tracks.num_tracks == 0 and tracks.num_inconsistent == 1  # one component: every view twice
    assert tracks.conflicts.view.size == 12 and len(tracks.conflicts.edges) == 31
    assert result.num_parts == 2 and result.num_matches_cut == 1 and result.num_components_lost == 0
    assert _parts(tracks.conflicts, result.part) == [[(v, 0) for v in range(6)], [(v, 1) for v in range(6)]]
    order = np.argsort(result.part, kind="stable")
    solved = triangulate_tracks(R, C, result.part[order], tracks.conflicts.view[order], xy[order])
    assert solved.valid.all()
    truth = np.stack([P, Q] if tracks.conflicts.feature[order][0] == 0 else [Q, P])
    assert np.abs(solved.points_in_world - truth).max() < 1e-9


def _wrong_keypoint(R, C, P, i, j, shift_px):
    """The projection of P in view j moved ``shift_px`` along its epipolar line from view i."""
    R_ji = R[j] @ R[i].T
    t_ji = R[j] @ (C[i] - C[j])
    x_i = np.r_[_project(R, C, P)[i], 1.0]
    line = so3.hat(t_ji) @ R_ji @ x_i  # x_j^T line = 0
    direction = np.array([line[1], -line[0]]) / np.hypot(line[0], line[1])
    return _project(R, C, P)[j] + shift_px / FOCAL * direction


def test_a_wrong_keypoint_hung_on_a_track_is_cut_off_and_the_track_kept():
    R, C = _cameras()
    P = np.array([2.0, 0.3, 10.0])
    wrong = _wrong_keypoint(R, C, P, 1, 3, 30.0)
    keypoints = [_project(R, C, P)[v][None] for v in range(6)]
    keypoints[3] = np.stack([keypoints[3][0], wrong])  # view 3: feature 0 true, 1 wrong
    links = _all_pairs(dict.fromkeys(range(6), 0)) + [(1, 0, 3, 1)]
    tracks, xy, result = _split(R, C, keypoints, links)
    assert tracks.num_inconsistent == 1 and tracks.conflicts.view.size == 7
    assert result.num_parts == 1 and result.num_matches_cut == 1
    assert _parts(tracks.conflicts, result.part) == [[(v, 0) for v in range(6)]]
    assert result.part[(tracks.conflicts.view == 3) & (tracks.conflicts.feature == 1)] == -1


def test_an_observation_that_misfits_the_rest_is_dropped_and_the_others_kept():
    R, C = _cameras()
    P = np.array([2.0, 0.3, 10.0])
    keypoints = [_project(R, C, P)[v][None] for v in range(6)]
    keypoints[3] = np.stack([keypoints[3][0], _wrong_keypoint(R, C, P, 1, 3, 30.0)])
    keypoints[5] = keypoints[5] + np.array([[0.0, 20.0 / FOCAL]])  # 20 px off the others
    links = _all_pairs(dict.fromkeys(range(6), 0)) + [(1, 0, 3, 1)]
    tracks, xy, result = _split(R, C, keypoints, links)
    assert result.num_parts == 1
    assert _parts(tracks.conflicts, result.part) == [[(v, 0) for v in range(5)]]
    assert result.num_matches_cut == 1 + 5  # the wrong match, and view 5's five matches
    part = result.part >= 0
    solved = triangulate_tracks(R, C, result.part[part], tracks.conflicts.view[part], xy[part])
    assert solved.valid.all() and np.abs(solved.points_in_world[0] - P).max() < 1e-9


def test_a_component_no_two_rays_agree_on_is_dropped():
    R, C = _cameras(4)
    rng = np.random.default_rng(2)
    keypoints = [rng.uniform(-0.3, 0.3, size=(2, 2)) for _ in range(4)]  # no point behind them
    links = [(0, 0, 1, 0), (1, 0, 2, 0), (2, 0, 3, 0), (3, 0, 0, 1), (0, 1, 1, 1)]
    tracks, xy, result = _split(R, C, keypoints, links)
    assert tracks.num_inconsistent == 1
    assert result.num_parts == 0 and result.num_components_lost == 1 and (result.part == -1).all()
