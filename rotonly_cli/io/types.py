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

import numpy as np


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
