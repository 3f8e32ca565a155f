"""Plain data exchanged between the readers/writers of `io/` and the rest of rotonly.

Conventions (architecture.md "Conventions"):
- Poses are ``R_cam_from_world`` (world -> camera) plus the camera centre in world
  coordinates: ``x_cam = R (X - c)``. This is OpenMVG's ``extrinsics`` and the paper's
  (eq:projectionEquation).
- Keypoints are held in **COLMAP's pixel convention** (the centre of the top-left pixel is
  (0.5, 0.5)). OpenMVG files use (0, 0) for that centre: the OpenMVG reader/writer adds /
  subtracts 0.5 to keypoints *and* to the principal point at the file boundary, nowhere
  else, so normalized coordinates never change.
- ``normalized`` are undistorted normalized image coordinates (x, y) with z = 1, computed
  by the reader with the camera model of the source tool (pycolmap for COLMAP cameras,
  OpenMVG's own formulas for OpenMVG intrinsics).
- Pairs are keyed ``(i, j)`` with ``i < j`` (view ids); ``matches[:, 0]`` indexes view
  i's keypoints, ``matches[:, 1]`` view j's. A relative pose, when present, is
  ``R_j_from_i`` / ``t_j_from_i`` (= COLMAP ``cam2_from_cam1`` with image1 = i).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import chain

import numpy as np

from rotonly_cli.errors import InputError

#: COLMAP models whose first two parameters are fx, fy (every other model: f first)
TWO_FOCAL_MODELS = ("PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE",
                    "RAD_TAN_THIN_PRISM_FISHEYE")


@dataclass
class Intrinsics:
    """One camera model. ``model`` is the source tool's own name (COLMAP ``PINHOLE`` ...,
    or OpenMVG ``pinhole_radial_k3`` ...); ``params`` are in that model's own order, in
    COLMAP's pixel convention (principal point +0.5 for OpenMVG models)."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray
    #: whether the source says the focal length is known: COLMAP's ``prior_focal_length``
    #: (False: a guess, e.g. 1.2 x the image size from COLMAP's front end); None: the source
    #: does not say (OpenMVG, simulations)
    prior_focal: bool | None = None

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (mean of fx, fy for two-focal COLMAP models)."""
        params = np.asarray(self.params, dtype=float).ravel()
        return float(params[:2].mean()) if self.model in TWO_FOCAL_MODELS else float(params[0])


@dataclass
class View:
    id: int
    name: str  # image file name relative to the image root
    intrinsics_id: int
    pose_id: int | None = None  # OpenMVG keeps a separate pose id; None -> same as ``id``
    # Image size as the source stored it per view (OpenMVG ``View.width/height``); None ->
    # take it from the intrinsics. Needed for views whose intrinsic is undefined.
    width: int | None = None
    height: int | None = None


@dataclass
class Pose:
    R_cam_from_world: np.ndarray  # (3, 3)
    center: np.ndarray  # (3,) camera centre in world coordinates

    @property
    def t_cam_from_world(self) -> np.ndarray:
        return -self.R_cam_from_world @ self.center


@dataclass
class PairMatches:
    i: int
    j: int
    matches: np.ndarray  # (m, 2) int64 keypoint indices into views i and j
    R_j_from_i: np.ndarray | None = None  # stored relative rotation, if any
    t_j_from_i: np.ndarray | None = None  # stored relative translation direction, if any
    config: str | None = None  # e.g. COLMAP TwoViewGeometry config name, "E" for OpenMVG e-matches
    verified: bool = True  # False: raw / putative matches


@dataclass
class Structure:
    """Triangulated points: ``points`` (N, 3) world coordinates, ``colors`` (N, 3) uint8,
    and per point a list of (view_id, keypoint_index) observations."""

    point_ids: np.ndarray  # (N,) int64
    points: np.ndarray  # (N, 3) float64
    colors: np.ndarray | None = None  # (N, 3) uint8
    observations: list[list[tuple[int, int]]] = field(default_factory=list)
    # Optional per point (k, 2) pixel positions of its observations (COLMAP convention),
    # aligned with ``observations``: OpenMVG stores them in each landmark (``x``).
    observation_pixels: list[np.ndarray] | None = None
    # Optional ``observations`` again as flat arrays (track_lengths (N,), view_feature (M, 2)
    # int64, as flat_observations returns them), set by producers that hold the tracks as
    # arrays (triangulation, scene.ids): the writers then skip the M Python tuples.
    # Whoever replaces ``observations`` must replace (or clear) it too.
    observation_arrays: tuple[np.ndarray, np.ndarray] | None = None

    def flat_observations(self) -> tuple[np.ndarray, np.ndarray]:
        """All observations as arrays, for the vectorised writers: ``track_lengths`` (N,)
        int64 and ``view_feature`` (M, 2) int64 rows (view_id, keypoint_index), tracks
        concatenated in point order. Read-only: they may be ``observation_arrays``."""
        if self.observation_arrays is not None:
            track_lengths, view_feature = self.observation_arrays
            if len(track_lengths) != len(self.observations):
                raise InputError("observation_arrays do not match observations", field="structure.observations")
            return track_lengths, view_feature
        track_lengths = np.fromiter(map(len, self.observations), dtype=np.int64,
                                    count=len(self.observations))
        total = int(track_lengths.sum())
        flat = np.fromiter(chain.from_iterable(chain.from_iterable(self.observations)),
                           dtype=np.int64, count=2 * total)
        return track_lengths, flat.reshape(total, 2)

    def flat_observation_pixels(self, track_lengths: np.ndarray) -> np.ndarray | None:
        """``observation_pixels`` concatenated to (M, 2) (None if not stored); InputError if
        their counts differ from ``track_lengths``."""
        if self.observation_pixels is None:
            return None
        blocks = [np.asarray(block, dtype=np.float64).reshape(-1, 2) for block in self.observation_pixels]
        if len(blocks) != len(track_lengths) or not np.array_equal(
                np.fromiter(map(len, blocks), dtype=np.int64, count=len(blocks)), track_lengths):
            raise InputError("observation_pixels do not match the observations",
                             field="structure.observation_pixels")
        return np.concatenate(blocks) if blocks else np.zeros((0, 2))


@dataclass
class SfMScene:
    """Everything a reader can know about a project."""

    views: dict[int, View] = field(default_factory=dict)
    intrinsics: dict[int, Intrinsics] = field(default_factory=dict)
    poses: dict[int, Pose] = field(default_factory=dict)  # keyed by view id
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)  # (n, 2) pixels, COLMAP convention
    normalized: dict[int, np.ndarray] = field(default_factory=dict)  # (n, 2) normalized (z = 1)
    pairs: dict[tuple[int, int], PairMatches] = field(default_factory=dict)
    structure: Structure | None = None
    root_path: str = ""  # image root (OpenMVG ``root_path``)
    source: str = ""  # "colmap-db", "openmvg", "colmap-model", "strecha", "simulation"

    def focal_px(self, view_ids) -> np.ndarray:
        """Focal length (px) of each of ``view_ids``; NaN for a view without intrinsics."""
        def focal(view_id: int) -> float:
            intrinsics = self.intrinsics.get(self.views[view_id].intrinsics_id) if view_id in self.views else None
            return intrinsics.focal_px if intrinsics is not None else float("nan")

        return np.array([focal(v) for v in view_ids], dtype=float)
