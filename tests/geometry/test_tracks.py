"""Track building from pairwise matches (geometry/tracks.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rotonly_cli.errors import InputError
from rotonly_cli.geometry.tracks import (
    build_tracks,
    compact_track_ids,
    gather_observations,
    node_numbers,
    pairs_in_track_chunks,
    pairs_within_tracks,
    ranks_within,
    segment_indices,
    track_starts,
)

from helpers import make_street_scene


def matches_from_scene(obs_point, obs_view, num_views, rng, chain_only: bool):
    """Per view a random keypoint order; pairwise matches of every (or consecutive) pair of a track."""
    feature = np.empty(obs_point.size, dtype=np.int64)
    for v in range(num_views):  # per-view shuffle, a loop over views only
        idx = np.flatnonzero(obs_view == v)
        feature[idx] = rng.permutation(idx.size)
    pairs: dict[tuple[int, int], list] = {}
    starts = np.flatnonzero(np.r_[True, obs_point[1:] != obs_point[:-1]])
    ends = np.r_[starts[1:], obs_point.size]
    for s, e in zip(starts, ends):
        members = list(range(s, e))
        links = zip(members[:-1], members[1:]) if chain_only else (
            (a, b) for k, a in enumerate(members) for b in members[k + 1:])
        for a, b in links:
            pairs.setdefault((int(obs_view[a]), int(obs_view[b])), []).append((feature[a], feature[b]))
    keys = list(pairs)
    return keys, [np.array(pairs[k]) for k in keys], feature


def canonical_partition(view, feature, group):
    """Set of frozensets of (view, feature) per group, for comparing partitions."""
    out: dict[int, set] = {}
    for v, f, g in zip(view.tolist(), feature.tolist(), group.tolist()):
        out.setdefault(g, set()).add((v, f))
    return {frozenset(s) for s in out.values()}


def test_tracks_reproduce_generating_tracks_from_chains():
    scene = make_street_scene(12, 300, seed=3)
    rng = np.random.default_rng(0)
    keys, matches, feature = matches_from_scene(scene.obs_point, scene.obs_view, 12, rng, chain_only=True)
    tracks = build_tracks(keys, matches)
    assert tracks.num_tracks == len(scene.points)
    assert tracks.num_inconsistent == 0
    assert canonical_partition(tracks.view, tracks.feature, tracks.track_id) == \
        canonical_partition(scene.obs_view, feature, scene.obs_point)
    # layout: sorted by (track, view), offsets/length consistent
    assert np.all(np.diff(tracks.track_id) >= 0)
    assert np.array_equal(np.diff(tracks.offsets), tracks.length)
    assert np.array_equal(np.bincount(tracks.track_id), tracks.length)


def test_all_pairs_matches_give_same_tracks():
    scene = make_street_scene(8, 120, seed=4)
    rng = np.random.default_rng(1)
    keys, matches, feature = matches_from_scene(scene.obs_point, scene.obs_view, 8, rng, chain_only=False)
    tracks = build_tracks(keys, matches)
    assert tracks.num_tracks == len(scene.points)
    assert tracks.num_observations == scene.obs_point.size


def test_inconsistent_track_dropped_and_min_length():
    # track A: (0,1)-(1,4)-(2,7); track B: (0,2)-(1,5)-(2,9)-(0,3)  (view 0 twice: dropped)
    # track C: (3,0)-(4,0) has length 2
    keys = [(0, 1), (1, 2), (2, 0), (3, 4)]
    matches = [np.array([[1, 4], [2, 5]]), np.array([[4, 7], [5, 9]]), np.array([[9, 3]]), np.array([[0, 0]])]
    tracks = build_tracks(keys, matches)
    assert tracks.num_inconsistent == 1
    assert tracks.num_tracks == 2
    assert tracks.view.tolist() == [0, 1, 2, 3, 4]
    assert tracks.feature.tolist() == [1, 4, 7, 0, 0]
    assert build_tracks(keys, matches, min_length=3).num_tracks == 1


def test_empty_and_gather():
    empty = build_tracks([], [])
    assert empty.num_tracks == 0 and empty.offsets.tolist() == [0]
    tracks = build_tracks([(0, 1)], [np.array([[2, 0], [0, 1]])])
    points = [np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.array([[5.0, 5.0], [6.0, 6.0]])]
    # track 0 = node (0, 0) + (1, 1); track 1 = (0, 2) + (1, 0)
    assert gather_observations(tracks, points)[:, 0].tolist() == [0.0, 6.0, 2.0, 5.0]
    # a view without points (no calibration) in between, as a flat empty array
    tracks = build_tracks([(0, 2)], [np.array([[2, 0], [0, 1]])])
    gathered = gather_observations(tracks, [points[0], np.zeros(0), points[1]])
    assert gathered.shape == (4, 2) and gathered[:, 0].tolist() == [0.0, 6.0, 2.0, 5.0]


def test_pairs_within_tracks():
    a, b = pairs_within_tracks(np.array([0, 3, 4, 6]))
    assert list(zip(a.tolist(), b.tolist())) == [(0, 1), (0, 2), (1, 2), (4, 5)]


def test_pairs_in_track_chunks_cut_at_tracks_within_the_budget():
    # tracks of 3, 1, 2, 0 and 4 observations: 3, 0, 1, 0 and 6 pairs
    offsets = np.array([0, 3, 4, 6, 6, 10])
    chunks = list(pairs_in_track_chunks(offsets, max_pairs=4))
    # a track with more pairs than the budget is a chunk of its own
    assert [(t0, t1) for t0, t1, _, _ in chunks] == [(0, 4), (4, 5)]
    a, b = pairs_within_tracks(offsets)
    for max_pairs in (1, 2, 3, 5, 100):
        parts = list(pairs_in_track_chunks(offsets, max_pairs=max_pairs))
        assert [t0 for t0, _, _, _ in parts[1:]] == [t1 for _, t1, _, _ in parts[:-1]] and parts[-1][1] == 5
        assert all(a_k.size <= max_pairs or t1 == t0 + 1 for t0, t1, a_k, _ in parts)
        np.testing.assert_array_equal(np.concatenate([a_k for _, _, a_k, _ in parts]), a)
        np.testing.assert_array_equal(np.concatenate([b_k for _, _, _, b_k in parts]), b)
    assert list(pairs_in_track_chunks(np.array([0]))) == []


def test_build_tracks_takes_int32_matches_and_rejects_negative_keypoints():
    matches = [np.array([[0, 5], [3, 2]], dtype=np.int32), np.array([[5, 7]], dtype=np.int64)]
    tracks = build_tracks([(0, 1), (1, 2)], matches)
    assert tracks.view.tolist() == [0, 1, 2, 0, 1] and tracks.feature.tolist() == [0, 5, 7, 3, 2]
    with pytest.raises(InputError, match="negative"):
        build_tracks([(0, 1)], [np.array([[0, -1]])])


@given(st.lists(st.integers(0, 40), max_size=60))
def test_compact_track_ids_are_numpy_unique_of_sorted_tracks(ids):
    obs_track = np.sort(np.asarray(ids, dtype=np.int64))
    distinct, index = compact_track_ids(obs_track)
    expected, inverse = np.unique(obs_track, return_inverse=True)
    np.testing.assert_array_equal(distinct, expected)
    np.testing.assert_array_equal(index, inverse.ravel())
    np.testing.assert_array_equal(obs_track[track_starts(obs_track)], expected)


@given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 6)), max_size=20))
def test_segment_indices_and_ranks_are_the_python_loops(segments):
    starts = np.array([start for start, _ in segments], dtype=np.int64)
    counts = np.array([count for _, count in segments], dtype=np.int64)
    np.testing.assert_array_equal(ranks_within(counts), [r for c in counts.tolist() for r in range(c)])
    np.testing.assert_array_equal(segment_indices(starts, counts),
                                  [s + r for s, c in zip(starts.tolist(), counts.tolist()) for r in range(c)])


def _keys(rows, num_feats=100):
    # (view_a, kp_a, view_b, kp_b) rows -> the (M, 2) node keys of minority_keypoint_matches
    rows = np.asarray(rows, dtype=np.int64)
    return np.stack([rows[:, 0] * num_feats + rows[:, 1], rows[:, 2] * num_feats + rows[:, 3]], axis=1)


def test_a_second_keypoint_of_one_match_is_the_minority():
    from rotonly_cli.geometry.tracks import minority_keypoint_matches

    # a point seen in views 0-3 (keypoint 0 each, all pairs matched), and a keypoint 7 of view 1
    # hung on it by one match from view 0 (a match moved along its epipolar line); a second
    # track of views 0-1 (keypoints 5, 6) is consistent
    track = [(a, 0, b, 0) for a in range(4) for b in range(a + 1, 4)]
    rows = track + [(0, 0, 1, 7), (0, 5, 1, 6)]
    drop = minority_keypoint_matches(_keys(rows), 100)
    assert drop.tolist() == [False] * len(track) + [True, False]


def test_a_single_match_against_fewer_than_three_is_kept():
    from rotonly_cli.geometry.tracks import minority_keypoint_matches

    # view 0's keypoint 0 matched to two keypoints of view 1, one match each: nothing tells
    # which is the point's, both kept; matched from a third view, one has two matches against
    # one: still kept; from a fourth, three against one: the single match is dropped
    assert minority_keypoint_matches(_keys([(0, 0, 1, 0), (0, 0, 1, 1)]), 100).tolist() == [False, False]
    rows = [(0, 0, 1, 0), (0, 0, 1, 1), (1, 0, 2, 0)]
    assert minority_keypoint_matches(_keys(rows), 100).tolist() == [False, False, False]
    rows += [(1, 0, 3, 0)]
    assert minority_keypoint_matches(_keys(rows), 100).tolist() == [False, True, False, False]
    assert not minority_keypoint_matches(np.zeros((0, 2), dtype=np.int64), 100).any()


@given(st.lists(st.integers(0, 40), min_size=1, max_size=60), st.integers(0, 200))
def test_node_numbers_matches_unique_on_either_path(keys, extra_space):
    """Both paths of node_numbers (the presence mask where the key space is at most twice the
    keys, np.unique beyond) give np.unique's sorted keys and its inverse."""
    keys = np.array(keys, dtype=np.int64).reshape(-1, 1)
    space = int(keys.max()) + 1 + extra_space
    nodes, place = node_numbers(keys, space)
    expected, inverse = np.unique(keys, return_inverse=True)
    assert np.array_equal(nodes, expected)
    assert np.array_equal(place.ravel(), inverse.ravel())
    assert place.shape == keys.shape and place.dtype == np.int32
