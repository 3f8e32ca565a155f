"""The largest set of views whose centres tracks fix up to one common scale (LiGT's solvable
set, algorithms.md §1.2): :func:`rigid_views`.

Pure numpy/scipy. The pairs of views inside each track are taken a chunk of tracks at a time
(tracks.pairs_in_track_chunks) and joined by an incremental union: every distinct view pair
keeps a label (the smallest pair of its body so far), and a chunk's links, deduplicated on
those labels, merge the bodies they touch. Memory: O(distinct view pairs + one chunk), never
the Σ L(L-1)/2 pairs of all tracks at once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from rotonly_cli.geometry.tracks import pairs_in_track_chunks, segment_indices, track_starts

__all__ = ["rigid_views"]

#: below this many possible pair keys (views²) the distinct view pairs are numbered with a
#: lookup table, above with sorted keys and a binary search
MAX_DENSE_KEYS = 4_000_000


def _pair_chunks(obs_view: np.ndarray, first: np.ndarray, capped: np.ndarray, num_views: int):
    """Per chunk of tracks: (the view pair key ``min * n + max`` of every pair of observations
    inside a track, in pairs_within_tracks order; whether each pair is in the same track as
    the next one)."""
    offsets = np.zeros(capped.size + 1, dtype=np.int64)
    np.cumsum(capped, out=offsets[1:])
    for t0, t1, a, b in pairs_in_track_chunks(offsets):
        view_a, view_b = obs_view[first[a]], obs_view[first[b]]
        keys = np.minimum(view_a, view_b) * num_views + np.maximum(view_a, view_b)
        track_of_pair = np.repeat(np.arange(t1 - t0), capped[t0:t1] * (capped[t0:t1] - 1) // 2)
        yield keys, track_of_pair[1:] == track_of_pair[:-1]


class _PairIds:
    """The distinct view pair keys (ascending) and each key's index among them."""

    def __init__(self, chunks, num_views: int):
        num_keys = num_views * num_views
        self.table = None
        if num_keys <= MAX_DENSE_KEYS:
            present = np.zeros(num_keys, dtype=bool)
            for keys, _ in chunks:
                present[keys] = True
            self.keys = np.flatnonzero(present)
            self.table = np.zeros(num_keys, dtype=np.int64)
            self.table[self.keys] = np.arange(self.keys.size)
        else:
            distinct = np.zeros(0, dtype=np.int64)
            for keys, _ in chunks:
                distinct = np.union1d(distinct, keys)
            self.keys = distinct

    def __call__(self, keys: np.ndarray) -> np.ndarray:
        return self.table[keys] if self.table is not None else np.searchsorted(self.keys, keys)


def _merged(label: np.ndarray, node_a: np.ndarray, node_b: np.ndarray) -> np.ndarray:
    """``label`` (per node, the smallest node of its body) after linking ``node_a[k]`` to
    ``node_b[k]``; the links deduplicated on the labels they join first."""
    label_a, label_b = label[node_a], label[node_b]
    apart = label_a != label_b
    if not apart.any():
        return label
    num_nodes = label.size
    joined = np.unique(np.minimum(label_a[apart], label_b[apart]) * num_nodes
                       + np.maximum(label_a[apart], label_b[apart]))
    roots, ends = np.unique(np.concatenate([joined // num_nodes, joined % num_nodes]), return_inverse=True)
    num_bodies, body = connected_components(
        sp.coo_matrix((np.ones(joined.size), (ends[:joined.size], ends[joined.size:])),
                      shape=(roots.size, roots.size)), directed=False)
    smallest = np.full(num_bodies, num_nodes, dtype=np.int64)
    np.minimum.at(smallest, body, roots)
    relabel = np.arange(num_nodes)
    relabel[roots] = smallest[body]
    return relabel[label]


def rigid_views(obs_track: np.ndarray, obs_view: np.ndarray, num_views: int,
                view_mask: np.ndarray | None = None, max_track_views: int = 64) -> np.ndarray:
    """(n,) bool: the largest set of views whose centres tracks fix up to one common scale.

    A track fixes the distances among its own views up to one scale: its base pair's baseline
    sets the depth of the point, which places every other view of the track (algorithms.md
    §1.1). Two such bodies share a scale when they share a baseline, i.e. two views; sharing
    one view leaves each free to scale about it. So the rigid sets are the connected components
    of the view pairs co-observed in a track, two pairs joined when a track holds both, and a
    view reached by two-view tracks only (a leaf of the view graph) or hinged on a single
    view keeps a distance no constraint decides: LiGT's least-squares solution is free to put
    it anywhere, and to shrink the rest. Views of ``view_mask`` only; a track's first
    ``max_track_views`` views stand for it. The largest set counts views, then pairs."""
    obs_track = np.asarray(obs_track, dtype=np.int64)
    obs_view = np.asarray(obs_view, dtype=np.int64)
    if view_mask is not None:
        keep = np.asarray(view_mask, dtype=bool)[obs_view]
        obs_track, obs_view = obs_track[keep], obs_view[keep]
    rigid = np.zeros(num_views, dtype=bool)
    if not obs_track.size:
        return rigid
    starts = track_starts(obs_track)
    length = np.diff(np.append(starts, obs_track.size))
    # a two-view body {a, b} joins only bodies that hold both a and b already: it adds no view
    # and links no two bodies that do not share a and b themselves. So the tracks of three or
    # more views decide, and without any the rigid set is the pair with the most tracks
    if not (length >= 3).any():
        two = starts[length == 2]
        pair = np.sort(np.stack([obs_view[two], obs_view[two + 1]], axis=1), axis=1)
        if pair.size:
            keys, counts = np.unique(pair[:, 0] * num_views + pair[:, 1], return_counts=True)
            best_pair = keys[np.argmax(counts)]
            rigid[[best_pair // num_views, best_pair % num_views]] = True
        return rigid
    starts, length = starts[length >= 3], length[length >= 3]
    capped = np.minimum(length, max_track_views)
    first = segment_indices(starts, capped)
    pair_ids = _PairIds(_pair_chunks(obs_view, first, capped, num_views), num_views)
    # the pairs of one track are consecutive: each is linked to the next of the same track
    label = np.arange(pair_ids.keys.size)
    for keys, same in _pair_chunks(obs_view, first, capped, num_views):
        node = pair_ids(keys)
        label = _merged(label, node[:-1][same], node[1:][same])
    # bodies numbered by their smallest pair, as connected_components numbers them
    _, component = np.unique(label, return_inverse=True)
    component = component.ravel()
    num_components = int(component.max()) + 1
    keys = pair_ids.keys
    pair_views = np.stack([keys // num_views, keys % num_views], axis=1)
    views_of = _views_of(np.repeat(component, 2), pair_views.ravel(), num_components, num_views)
    pairs = np.bincount(component, minlength=num_components)
    # Each component is rigid, but two of them can share two views without a track holding
    # both: (0, 1, 2), (0, 2, 3) and (1, 3, 4) tie 1-3 in the first two bodies and in the
    # third, so the third shares their baseline. Merge bodies that share two views until none
    # do (sequential captures otherwise lose their far end)
    while num_components > 1:
        shared = (views_of @ views_of.T).tocoo()
        link = (shared.data >= 2) & (shared.row < shared.col)
        if not link.any():
            break
        num_components, merged = connected_components(
            sp.coo_matrix((np.ones(int(link.sum())), (shared.row[link], shared.col[link])),
                          shape=views_of.shape[:1] * 2), directed=False)
        rows, cols = views_of.nonzero()
        views_of = _views_of(merged[rows], cols, num_components, num_views)
        pairs = np.bincount(merged, weights=pairs, minlength=num_components)
    size = np.asarray(views_of.sum(axis=1)).ravel()
    best = int(np.lexsort((-pairs, -size))[0])
    return views_of[best].toarray().ravel() > 0


def _views_of(body: np.ndarray, view: np.ndarray, num_bodies: int, num_views: int) -> sp.csr_matrix:
    """(num_bodies, num_views) 0/1 int matrix: which views each body holds (from the
    ``(body, view)`` incidences, repeats allowed)."""
    incidence = sp.csr_matrix((np.ones(body.size, dtype=np.int64), (body, view)), shape=(num_bodies, num_views))
    incidence.data[:] = 1
    return incidence
