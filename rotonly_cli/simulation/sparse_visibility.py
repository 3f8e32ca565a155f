"""Which simulated points each camera sees, held sparse: per view the ascending ids of the
points it sees (rows of a CSR matrix), never a (views x points) array, so memory grows with the
observations and time with the observations plus views x groups.

Only plausible (camera, point) combinations are projected. Cameras are taken in groups of
consecutive ones (neighbours along every set-up's trajectory); a point outside a cone that
bounds the whole group's fields of view (apex at the group's mean centre, half-angle the
image-corner angle + the spread of the group's optical axes + the angle the group's extent
subtends at the point) is in none of their images. Groups are halved recursively, each half
testing only its parent's candidates, so culling costs about points x log(views) where the
cones are narrow, not points x views. The remaining candidates get exactly the dense test
(same einsum, same comparisons): numpy's einsum gives the same bits for a subset of cameras
and points as for all of them (tests/simulation/test_sparse_visibility.py checks the results
against the dense computation), so the kept points and their image positions do not change.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: consecutive cameras (at most) that project their candidate points together
CAMERAS_PER_GROUP = 32
#: at most this many (camera, point) projections in one einsum (~48 MB of float64)
PROJECTIONS_PER_BLOCK = 1 << 21
#: the bounding cone is widened by this angle (radians) so rounding never culls a seen point
CONE_MARGIN = 1e-6
#: in front of the camera: depth above this (the dense test's threshold)
MIN_DEPTH = 1e-9


@dataclass
class SparseVisibility:
    """View v sees the points ``point_ids[offsets[v]:offsets[v + 1]]`` (ascending); the k-th
    of them is view v's keypoint k."""

    offsets: np.ndarray  # (num_views + 1,) int64
    point_ids: np.ndarray  # (num_observations,) int64
    num_points: int

    @classmethod
    def from_observations(cls, views: np.ndarray, points: np.ndarray, num_views: int,
                          num_points: int) -> SparseVisibility:
        """From (view, point) observations in any order, without repeats."""
        order = np.lexsort((points, views))
        offsets = np.zeros(num_views + 1, dtype=np.int64)
        np.cumsum(np.bincount(views, minlength=num_views), out=offsets[1:])
        return cls(offsets, np.asarray(points, dtype=np.int64)[order], int(num_points))

    @property
    def num_views(self) -> int:
        return len(self.offsets) - 1

    def points_of(self, view: int) -> np.ndarray:
        return self.point_ids[self.offsets[view]:self.offsets[view + 1]]

    def observation_views(self) -> np.ndarray:
        """(num_observations,) the view of each observation."""
        return np.repeat(np.arange(self.num_views, dtype=np.int64), np.diff(self.offsets))

    def dense(self) -> np.ndarray:
        """(num_views, num_points) bool: O(views x points) memory, for small problems."""
        seen = np.zeros((self.num_views, self.num_points), dtype=bool)
        seen[self.observation_views(), self.point_ids] = True
        return seen

    def tracks(self) -> tuple[np.ndarray, np.ndarray]:
        """Per point its observations, as ``Structure.flat_observations`` gives them:
        ``track_lengths`` (num_points,) and ``view_feature`` (num_observations, 2) rows (view,
        keypoint index), points in id order, each track by view."""
        views = self.observation_views()
        keypoints = np.arange(len(self.point_ids), dtype=np.int64) - np.repeat(self.offsets[:-1],
                                                                               np.diff(self.offsets))
        by_point = np.argsort(self.point_ids, kind="stable")  # stable: views ascending in a track
        track_lengths = np.bincount(self.point_ids, minlength=self.num_points).astype(np.int64)
        return track_lengths, np.column_stack([views[by_point], keypoints[by_point]])


class TrackLists(Sequence):
    """``Structure.observations`` of flat tracks (``SparseVisibility.tracks``), made per point
    when asked instead of one Python tuple per observation (read-only)."""

    def __init__(self, track_lengths: np.ndarray, view_feature: np.ndarray):
        self._starts = np.concatenate([[0], np.cumsum(track_lengths)]).astype(np.int64)
        self._view_feature = view_feature

    def __len__(self) -> int:
        return len(self._starts) - 1

    def __getitem__(self, point):
        if isinstance(point, slice):
            return [self[k] for k in range(*point.indices(len(self)))]
        if not -len(self) <= point < len(self):
            raise IndexError(point)
        point %= len(self)
        rows = self._view_feature[self._starts[point]:self._starts[point + 1]].tolist()
        return [tuple(row) for row in rows]


def shared_keypoints(visibility: SparseVisibility, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """The keypoint indices in view i and in view j of the points both see, by point id."""
    seen_i, seen_j = visibility.points_of(i), visibility.points_of(j)
    where = np.searchsorted(seen_j, seen_i)
    found = where < len(seen_j)
    found[found] = seen_j[where[found]] == seen_i[found]
    return np.flatnonzero(found), where[found]


def visible_observations(points: np.ndarray, R_cam_from_world: np.ndarray, centers: np.ndarray,
                         half_extent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(views, point indices) of every camera-point combination where the point is in front
    of the camera (depth > MIN_DEPTH) and inside its image (|x| < half_extent, normalized),
    in no particular order. The cameras are halved recursively, each half keeping the points
    inside its bounding cone, down to groups of CAMERAS_PER_GROUP that project them."""
    axes = R_cam_from_world[:, 2] / np.linalg.norm(R_cam_from_world[:, 2], axis=1, keepdims=True)
    corner_angle = float(np.arctan(np.hypot(*half_extent)))
    views, seen = [], []
    pending = [(0, len(centers), np.arange(len(points)))]  # camera range [first, stop), candidate points
    while pending:
        first, stop, candidates = pending.pop()
        group = slice(first, stop)
        candidates = candidates[_inside_group_cone(points[candidates], centers[group], axes[group], corner_angle)]
        if stop - first > CAMERAS_PER_GROUP:
            middle = (first + stop) // 2
            pending += [(middle, stop, candidates), (first, middle, candidates)]
            continue
        step = max(1, PROJECTIONS_PER_BLOCK // (stop - first))
        for start in range(0, len(candidates), step):
            block = candidates[start:start + step]
            view, index = np.nonzero(_in_image(points[block], R_cam_from_world[group], centers[group], half_extent))
            views.append(view + first)
            seen.append(block[index])
    if not views:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return (np.concatenate(views).astype(np.int64, copy=False),
            np.concatenate(seen).astype(np.int64, copy=False))


def _in_image(points: np.ndarray, R_cam_from_world: np.ndarray, centers: np.ndarray,
              half_extent: np.ndarray) -> np.ndarray:
    """(cameras, points) bool, the dense simulation's test verbatim."""
    X_cam = np.einsum("vab,vnb->vna", R_cam_from_world, points[None] - centers[:, None])  # (n, B, 3)
    depth = X_cam[..., 2]
    safe = np.where(depth > MIN_DEPTH, depth, 1.0)
    x = X_cam[..., :2] / safe[..., None]
    return (depth > MIN_DEPTH) & (np.abs(x[..., 0]) < half_extent[0]) & (np.abs(x[..., 1]) < half_extent[1])


def _inside_group_cone(points: np.ndarray, centers: np.ndarray, axes: np.ndarray,
                       corner_angle: float) -> np.ndarray:
    """Ascending indices of the points that may be in some image of the group: a point p seen
    by camera v makes an angle below ``corner_angle`` with v's axis a_v; with m the mean centre,
    ā the mean axis, ρ = max |c_v - m| and d = |p - m| > ρ, angle(ā, p - m) ≤ angle(ā, a_v) +
    angle(a_v, p - c_v) + angle(p - c_v, p - m) < spread + corner_angle + asin(ρ / d)."""
    mean_center = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - mean_center, axis=1).max())
    mean_axis = axes.mean(axis=0)
    length = float(np.linalg.norm(mean_axis))
    if length < 1e-6:
        return np.arange(len(points))
    mean_axis /= length
    spread = float(np.arccos(np.clip(axes @ mean_axis, -1.0, 1.0)).max())
    base = corner_angle + spread + CONE_MARGIN
    if base >= np.pi:
        return np.arange(len(points))
    offset = points - mean_center
    distance = np.sqrt(np.einsum("ij,ij->i", offset, offset))
    along = offset @ mean_axis
    near = distance <= radius * (1.0 + 1e-9) + 1e-9
    half_angle = base + np.arcsin(np.minimum(1.0, radius / np.where(near, 1.0, distance)))
    inside = along >= np.cos(np.minimum(half_angle, np.pi)) * distance
    return np.flatnonzero(near | inside)
