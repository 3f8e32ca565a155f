"""Feature tracks from pairwise matches (union-find over (view, keypoint) nodes).

Pure numpy/scipy. A track is a connected component of the observation graph whose
nodes are ``(view, keypoint)`` and whose edges are the pairwise matches. Components that
contain two different keypoints of the same view are inconsistent and left out (OpenMVG
``TracksBuilder::Filter`` does the same); on request their nodes and matches are kept
(:class:`ConflictGraph`), for geometry.track_split to cut into consistent parts once the
poses are known. The union-find is done in one call to
``scipy.sparse.csgraph.connected_components``, not with a Python loop per match.

Layout of :class:`Tracks`: flat observation arrays sorted by ``(track_id, view)``;
observations of track ``t`` are ``offsets[t]:offsets[t+1]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from rotonly_cli.errors import InputError

__all__ = ["Tracks", "ConflictGraph", "build_tracks", "tracks_from_arrays", "gather_observations",
           "pairs_within_tracks", "pairs_in_track_chunks", "segment_sums"]


@dataclass(frozen=True)
class ConflictGraph:
    """The components :func:`build_tracks` leaves out because they see one view twice (a wrong
    match hung a second keypoint of a view on a track, or merged two tracks): their
    ``(view, feature)`` nodes, each node's component (0..K-1) and the matches between them."""

    view: np.ndarray  # (N_nodes,) int64 view index
    feature: np.ndarray  # (N_nodes,) int64 keypoint index inside that view
    component: np.ndarray  # (N_nodes,) int64, 0..num_components-1
    edges: np.ndarray  # (M, 2) int32 (int64 beyond 2^31 nodes) node indices of the matches, both ends in one component

    @property
    def num_components(self) -> int:
        return int(self.component.max()) + 1 if self.component.size else 0


@dataclass(frozen=True)
class Tracks:
    """Flat track storage; all observation arrays are (N_obs,) and sorted by (track, view)."""

    track_id: np.ndarray  # (N_obs,) int64, 0..num_tracks-1, non-decreasing
    view: np.ndarray  # (N_obs,) int64 view index
    feature: np.ndarray  # (N_obs,) int64 keypoint index inside that view
    offsets: np.ndarray  # (num_tracks + 1,) int64 start of each track in the flat arrays
    length: np.ndarray  # (num_tracks,) int64 number of observations (= distinct views)
    num_inconsistent: int = 0  # components dropped because they saw one view twice
    conflicts: ConflictGraph | None = None  # those components, when build_tracks was asked to keep them

    @property
    def num_tracks(self) -> int:
        return int(self.length.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.track_id.shape[0])

    def subset(self, keep_track: np.ndarray) -> Tracks:
        """Tracks where ``keep_track`` (num_tracks,) bool is True, renumbered 0..k-1."""
        keep_track = np.asarray(keep_track, dtype=bool)
        keep_obs = keep_track[self.track_id]
        new_id = np.cumsum(keep_track) - 1
        return tracks_from_arrays(new_id[self.track_id[keep_obs]], self.view[keep_obs],
                                  self.feature[keep_obs], num_inconsistent=self.num_inconsistent)


def tracks_from_arrays(track_id: np.ndarray, view: np.ndarray, feature: np.ndarray,
                       num_inconsistent: int = 0) -> Tracks:
    """Build :class:`Tracks` from unsorted observation arrays (track ids must be 0..T-1 dense)."""
    track_id = np.asarray(track_id, dtype=np.int64)
    view = np.asarray(view, dtype=np.int64)
    feature = np.asarray(feature, dtype=np.int64)
    if not (track_id.shape == view.shape == feature.shape) or track_id.ndim != 1:
        raise InputError("track_id, view and feature must be 1-D arrays of one length", field="track_id")
    order = np.lexsort((view, track_id))
    track_id, view, feature = track_id[order], view[order], feature[order]
    num_tracks = int(track_id[-1]) + 1 if track_id.size else 0
    length = np.bincount(track_id, minlength=num_tracks).astype(np.int64)
    offsets = np.zeros(num_tracks + 1, dtype=np.int64)
    np.cumsum(length, out=offsets[1:])
    return Tracks(track_id, view, feature, offsets, length, int(num_inconsistent))


def node_numbers(keys: np.ndarray, key_space: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct ``keys`` sorted, each key's place among them) of non-negative integer
    keys below ``key_space`` (default: the largest key + 1; keys of any shape; places int32
    below 2^31 distinct keys).
    np.unique and a binary search of every key, unless the key space is at most twice the
    keys (views x keypoints against the ends of a dense view graph's matches): then a
    presence mask over the key space and its running count, linear in the keys (the
    1000-view recipe's 40 M match ends: 7.4 -> 0.5 s; the mask and counts: ≤ 10 bytes per
    key beside them)."""
    keys = np.asarray(keys)
    if key_space is None:
        key_space = int(keys.max()) + 1 if keys.size else 0
    if 0 < key_space <= 2 * keys.size and key_space < 2**31:
        present = np.zeros(key_space, dtype=bool)
        present[keys] = True
        place = np.cumsum(present, dtype=np.int32)
        place -= 1
        return np.flatnonzero(present), place[keys]
    nodes = np.unique(keys)
    return nodes, np.searchsorted(nodes, keys).astype(np.int32 if nodes.size < 2**31 else np.int64)


def build_tracks(pair_keys: Sequence[tuple[int, int]], pair_matches: Sequence[np.ndarray],
                 min_length: int = 2, keep_conflicts: bool = False) -> Tracks:
    """Tracks from pairwise matches.

    Args:
        pair_keys: ``(i, j)`` view indices per pair (any order; ``matches[:, 0]`` is in view i).
        pair_matches: per pair an ``(m, 2)`` int array of keypoint indices (view i, view j).
        min_length: drop tracks with fewer observations.
        keep_conflicts: keep the components that see a view twice in ``Tracks.conflicts``.

    Returns:
        :class:`Tracks`; track ids are ordered by their smallest (view, feature) node.
        Components that contain two keypoints of one view are left out
        (counted in ``num_inconsistent``; with ``keep_conflicts`` in ``conflicts``).
    """
    from scipy.sparse import coo_matrix  # lazily, like scene.view_graph
    from scipy.sparse.csgraph import connected_components

    if len(pair_keys) != len(pair_matches):
        raise InputError("pair_keys and pair_matches differ in length", field="pair_matches")
    matches_of = [np.asarray(matches).reshape(-1, 2) for matches in pair_matches]
    counts = np.array([len(matches) for matches in matches_of], dtype=np.int64)
    num_edges = int(counts.sum())
    if num_edges == 0:
        empty = np.zeros(0, dtype=np.int64)
        return Tracks(empty, empty, empty, np.zeros(1, dtype=np.int64), empty, 0)
    filled = [(i, j, matches) for (i, j), matches in zip(pair_keys, matches_of) if len(matches)]
    if min(min(i, j, int(matches.min())) for i, j, matches in filled) < 0:
        raise InputError("negative view or keypoint index in matches", field="pair_matches")
    num_feats = max(int(matches.max()) for _, _, matches in filled) + 1
    # one int64 key per match end and (view, feature) node, filled edge by edge: ends
    # [0, M) in view i, [M, 2M) in view j (no per-edge lists, no view / feature arrays per end)
    node_key = np.empty(2 * num_edges, dtype=np.int64)
    start = 0
    for (i, j), matches in zip(pair_keys, matches_of):
        stop = start + len(matches)
        np.add(matches[:, 0], i * num_feats, out=node_key[start:stop], dtype=np.int64, casting="unsafe")
        np.add(matches[:, 1], j * num_feats, out=node_key[num_edges + start:num_edges + stop], dtype=np.int64,
               casting="unsafe")
        start = stop
    # the node list is sorted by (view, feature), each end numbered by its node
    unique_keys, node_of_end = node_numbers(node_key)
    del node_key
    num_nodes = unique_keys.shape[0]
    graph = coo_matrix((np.ones(num_edges, dtype=np.int8),
                        (node_of_end[:num_edges], node_of_end[num_edges:])),
                       shape=(num_nodes, num_nodes))
    _, label = connected_components(graph, directed=False)
    node_view = unique_keys // num_feats
    node_feat = unique_keys % num_feats
    # inconsistent component: two nodes with one view (duplicates after sorting by label, view)
    order = np.lexsort((node_view, label))
    same = (label[order][1:] == label[order][:-1]) & (node_view[order][1:] == node_view[order][:-1])
    bad_label = np.unique(label[order][1:][same])
    component_size = np.bincount(label)
    keep_label = component_size >= max(min_length, 1)
    keep_label[bad_label] = False
    keep_node = keep_label[label]
    # dense renumbering in order of first node (labels already follow node order)
    new_id = np.cumsum(keep_label) - 1
    tracks = tracks_from_arrays(new_id[label[keep_node]], node_view[keep_node], node_feat[keep_node],
                                num_inconsistent=int(bad_label.size))
    if not keep_conflicts:
        return tracks
    conflicting = np.zeros(component_size.size, dtype=bool)
    conflicting[bad_label] = True
    node_conflicting = conflicting[label]
    node_index = np.cumsum(node_conflicting) - 1  # node -> its row among the conflicting ones
    end_a, end_b = node_of_end[:num_edges], node_of_end[num_edges:]
    edge_kept = node_conflicting[end_a]  # both ends share a component
    component = np.cumsum(conflicting) - 1
    conflicts = ConflictGraph(node_view[node_conflicting], node_feat[node_conflicting],
                              component[label[node_conflicting]],
                              np.stack([node_index[end_a[edge_kept]], node_index[end_b[edge_kept]]],
                                       axis=1).astype(np.int32 if node_index.size < 2**31 else np.int64))
    return replace(tracks, conflicts=conflicts)


def gather_observations(tracks: Tracks | ConflictGraph, per_view_points: Sequence[np.ndarray]) -> np.ndarray:
    """Per observation (or conflict node) the row ``per_view_points[view][feature]``, batched: (N_obs, d)."""
    sizes = np.array([len(p) for p in per_view_points], dtype=np.int64)
    start = np.zeros(len(sizes) + 1, dtype=np.int64)
    np.cumsum(sizes, out=start[1:])
    if np.any(tracks.view >= len(sizes)) or np.any(tracks.feature >= sizes[tracks.view]):
        raise InputError("track observation refers to a keypoint that does not exist", field="per_view_points")
    arrays = [np.asarray(p, dtype=float) for p in per_view_points]
    # a view without points (no calibration: no normalized keypoints) may come as a flat
    # empty array; it takes the others' width
    width = next((a.reshape(len(a), -1).shape[1] for a in arrays if a.size), 0)
    stacked = np.concatenate([a.reshape(len(a), width) for a in arrays])
    return stacked[start[tracks.view] + tracks.feature]


def ranks_within(lengths: np.ndarray) -> np.ndarray:
    """0, 1, ..., k-1 for every segment of length k in ``lengths``, concatenated."""
    lengths = np.asarray(lengths, dtype=np.int64)
    return np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths)


def segment_indices(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The positions ``starts[k], ..., starts[k] + counts[k] - 1`` of every segment k,
    concatenated (the first ``counts[k]`` elements of segments that begin at ``starts[k]``)."""
    return np.repeat(np.asarray(starts, dtype=np.int64), counts) + ranks_within(counts)


def track_starts(obs_track: np.ndarray) -> np.ndarray:
    """Index of each track's first observation, ``obs_track`` grouped by track (non-decreasing)."""
    if not obs_track.size:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.r_[True, obs_track[1:] != obs_track[:-1]])


def compact_track_ids(obs_track: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct track ids ascending, each observation's index among them) of ``obs_track``
    grouped by track: ``np.unique(obs_track, return_inverse=True)`` without its sort."""
    starts = track_starts(obs_track)
    first = np.zeros(obs_track.size, dtype=np.int64)
    first[starts] = 1
    return obs_track[starts], np.cumsum(first) - 1


def in_tracks_of_two(obs_track: np.ndarray, selected: np.ndarray) -> np.ndarray:
    """``selected`` (per observation, bool) without the observations left alone in their track
    (``obs_track``: track id per observation)."""
    counts = np.bincount(obs_track[selected], minlength=int(obs_track.max()) + 1 if obs_track.size else 0)
    return selected & (counts[obs_track] >= 2)


def pairs_within_tracks(offsets: np.ndarray, max_pairs: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All ordered observation pairs ``(a, b)``, ``a < b``, inside each track; vectorised.

    ``offsets``: (T+1,) track starts. Returns flat observation indices ``(a, b)``, ordered
    by track then a then b (OpenMVG's ``i < j`` scan order). The count is Σ L(L-1)/2.
    """
    offsets = np.asarray(offsets, dtype=np.int64)
    length = np.diff(offsets)
    num_obs = int(offsets[-1])
    track_of_obs = np.repeat(np.arange(length.size), length)
    position = np.arange(num_obs) - offsets[track_of_obs]
    num_partners = length[track_of_obs] - 1 - position  # obs a pairs with the ones after it
    total = int(num_partners.sum())
    if max_pairs is not None and total > max_pairs:
        raise InputError(f"{total} observation pairs exceed max_pairs={max_pairs}", field="offsets")
    a = np.repeat(np.arange(num_obs), num_partners)
    first = np.zeros(num_obs + 1, dtype=np.int64)
    np.cumsum(num_partners, out=first[1:])
    b = a + 1 + (np.arange(total) - np.repeat(first[:-1], num_partners))
    return a, b


#: the observation pairs inside tracks are enumerated at most about this many at a time
#: (pairs_in_track_chunks): a few int64 / float arrays per pair, tens of MB, whatever the
#: number of tracks (a track of L views has L(L-1)/2 pairs: 400 000 observations in tracks of
#: ~28 views make 8 M pairs, ~1 GB of index and value arrays in one piece)
PAIRS_PER_CHUNK = 1 << 19


def pairs_in_track_chunks(offsets: np.ndarray, max_pairs: int | None = None):
    """:func:`pairs_within_tracks` of consecutive track ranges [t0, t1) holding at most
    ``max_pairs`` pairs each (or a single track, however long): yields ``(t0, t1, a, b)``
    with flat observation indices in ``offsets``' numbering, the same pairs in the same order
    as one call over all tracks. ``max_pairs`` None: :data:`PAIRS_PER_CHUNK`."""
    max_pairs = PAIRS_PER_CHUNK if max_pairs is None else max_pairs
    offsets = np.asarray(offsets, dtype=np.int64)
    length = np.diff(offsets)
    pairs_before = np.zeros(length.size + 1, dtype=np.int64)
    np.cumsum(length * (length - 1) // 2, out=pairs_before[1:])
    start = 0
    while start < length.size:
        stop = int(np.searchsorted(pairs_before, pairs_before[start] + max_pairs, side="right")) - 1
        stop = min(max(stop, start + 1), length.size)
        a, b = pairs_within_tracks(offsets[start:stop + 1] - offsets[start])
        yield start, stop, a + offsets[start], b + offsets[start]
        start = stop


def segment_sums(components: np.ndarray, segment: np.ndarray, num_segments: int) -> np.ndarray:
    """Per-segment sums of component-major values, (k, N) -> (k, num_segments): one
    ``bincount`` per component (k is small), none over the N observations or matches."""
    return np.stack([np.bincount(segment, weights=c, minlength=num_segments) for c in components])


#: GRRM's evaluation and the robust LiGT's rounds are cut into this many parts, each summed
#: on its own and the sums added in order, whether the parts run one after the other or side
#: by side (a forked helper, runtime.parallel.ForkedPeer): the numbers do not depend on --jobs.
#: Two: the machines this runs on have two cores or more, and a part costs one extra set of sums
EVALUATION_PARTS = 2


def even_ranges(sizes: np.ndarray, parts: int) -> list[tuple[int, int]]:
    """Up to ``parts`` consecutive index ranges [a, b) of ``sizes`` with about equal sums
    (each cut at the index boundary nearest to its share; empty ranges dropped): how GRRM
    and the robust LiGT cut their work into parts that one or two processes evaluate."""
    sizes = np.asarray(sizes, dtype=np.int64)
    before = np.concatenate([[0], np.cumsum(sizes)])
    cuts = [int(np.argmin(np.abs(before - before[-1] * k / parts))) for k in range(1, parts)]
    bounds = [0] + cuts + [len(sizes)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


#: a single-match keypoint is the minority when its view's keypoint in the track has at least
#: this many matches (the point matched from three views or more); with any majority, castle-P19's
#: repeated windows and a sequential capture's weak link lost accuracy (docs/tuning.md)
MINORITY_MAJORITY_MATCHES = 3


def minority_keypoint_matches(node_keys: np.ndarray, num_feats: int) -> np.ndarray:
    """(M,) bool: the matches with an end on a keypoint of a single match whose track (the
    connected component of the match graph) sees the same view through a keypoint of at least
    :data:`MINORITY_MAJORITY_MATCHES` matches.

    ``node_keys``: (M, 2) int64 keys ``view * num_feats + keypoint`` of each match's two ends
    (:func:`build_tracks`' numbering). A track sees a view once. A match moved along its
    epipolar line passes every two-view test and hangs a second keypoint of a view on the
    track with that one match, where the point's own keypoint has a match per view it is
    matched in; GRRM's V_ik (eq:GRRMRes1) would weigh it by its wrong parallax, and LiGT
    drops the whole track. Anything less clear-cut is kept (two tracks merged, a keypoint of
    two matches against one of three: docs/tuning.md)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    node_keys = np.asarray(node_keys, dtype=np.int64).reshape(-1, 2)
    if not len(node_keys):
        return np.zeros(0, dtype=bool)
    nodes, node_of_end = node_numbers(node_keys)
    n = nodes.size
    _, label = connected_components(coo_matrix((np.ones(len(node_of_end), dtype=np.int8),
                                                (node_of_end[:, 0], node_of_end[:, 1])), shape=(n, n)),
                                    directed=False)
    degree = np.bincount(node_of_end.ravel(), minlength=n)
    # each (track, view)'s most matches on one keypoint: one reduceat over the nodes so sorted
    view = nodes // num_feats
    order = np.lexsort((view, label))
    first = np.flatnonzero(np.r_[True, (np.diff(label[order]) != 0) | (np.diff(view[order]) != 0)])
    group = np.empty(n, dtype=np.int64)
    group[order] = np.repeat(np.arange(first.size), np.diff(np.r_[first, n]))
    most = np.maximum.reduceat(degree[order], first)
    minority = (degree == 1) & (most[group] >= MINORITY_MAJORITY_MATCHES)
    return minority[node_of_end[:, 0]] | minority[node_of_end[:, 1]]
