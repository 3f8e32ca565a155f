"""The paper's five two-view simulation scenes (rotation_only.tex §"Default Settings",
§"Scene Identification"; algorithms.md §6).

All scenes share the camera poses of OpenGV's ``Standard`` experiment:

* view i (camera 1): centre at the origin, ``R_cam_from_world = I`` -> world = camera-i frame;
* view j (camera 2): centre uniform in a ball of radius ``max_parallax`` (2 m; the paper says
  "spherical space of radius 2 m", OpenGV itself uses the cube [-2, 2]^3); rotation built from
  roll/pitch/yaw uniform in [-0.5, 0.5] rad about x, y, z as ``Rz Ry Rx``. OpenGV's rotation
  is camera->world, so ``R_cam_from_world = (Rz Ry Rx)^T``.

Scenes (points are re-drawn until ``num_points`` are in front of both cameras, z > 0, and
inside both ``image_size`` images):

* ``standard``: points uniform in a ball of radius ``scene_radius`` (20 m) at the origin.
* ``planar`` (PlanarScene): points on the plane Z = ``plane_depth`` (10 m), which contains
  neither camera (|c_j| <= 2 < 10).
* ``holoplane``: points on a square plane of side 2*``scene_radius``/2 = 20 m through both
  camera centres and (0, 0, 1) (paper §"Scene Identification"): rank Pˢ = 1.
* ``rankregular_line``: points on a random line in the plane Z = ``plane_depth``.
* ``pure_rotation``: both centres at the origin (t_ij = 0), points as in ``standard``.

Observations are normalized image coordinates (z = 1, principal point at the image centre,
square pixels of focal ``focal``). Noise (documented choice): the paper draws the pixel noise
from "U(0, n)" without saying per axis or radial; ``noise_model="uniform"`` (default) reads it
as a displacement of magnitude U(0, n) px in a uniformly random direction, ``"gaussian"``
adds N(0, n²) px per axis, ``"opengv"`` adds U(-n, n) px per axis (OpenGV's MATLAB helper).
The focal length is not stated in the paper; the default 800 px is OpenGV's (algorithms.md §6),
i.e. a half field of view of atan(480/800) ≈ 31° at 960×960.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.io import atomic

SCENES: tuple[str, ...] = ("standard", "planar", "holoplane", "rankregular_line", "pure_rotation")
NOISE_MODELS: tuple[str, ...] = ("uniform", "gaussian", "opengv")

_MAX_POSE_ATTEMPTS = 50  # pose re-draws when a scene cannot show enough points in both images
_MAX_POINT_BATCHES = 200  # point batches per pose before re-drawing the pose


@dataclass
class TwoViewProblem:
    """One simulated edge (i, j). World = camera-i frame (R_i = I, c_i = 0)."""

    R_j_from_i: np.ndarray  # (3, 3) ground truth R_ij = R_j R_i^T
    t_j_from_i: np.ndarray  # (3,) ground truth t_ij = R_j (c_i - c_j) (not normalised; 0 for pure rotation)
    x_i: np.ndarray  # (m, 2) noisy normalized coordinates in view i
    x_j: np.ndarray  # (m, 2) noisy normalized coordinates in view j
    x_i_true: np.ndarray  # (m, 2) noise-free
    x_j_true: np.ndarray  # (m, 2)
    points_in_i: np.ndarray  # (m, 3) points in the camera-i (= world) frame
    center_j: np.ndarray  # (3,) camera-j centre in the world (= camera-i) frame
    scene: str
    focal: float
    image_size: tuple[int, int]  # (width, height) px
    noise_px: float
    noise_model: str = "uniform"
    seed: int | None = None
    extra: dict = field(default_factory=dict)  # scene parameters (plane normal, line, ...)

    @property
    def num_points(self) -> int:
        return int(self.x_i.shape[0])

    @property
    def R_j_cam_from_world(self) -> np.ndarray:
        return self.R_j_from_i  # R_i = I

    @property
    def translation_direction(self) -> np.ndarray:
        """Unit t_ij, or zeros for a pure rotation."""
        n = np.linalg.norm(self.t_j_from_i)
        return self.t_j_from_i / n if n > 0 else np.zeros(3)


# ----------------------------------------------------------------------------- poses
def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def bounded_rotation(rng: np.random.Generator, max_angle: float = 0.5) -> np.ndarray:
    """OpenGV ``generateBoundedR``: Rz Ry Rx with each angle uniform in [-max_angle, max_angle]."""
    roll, pitch, yaw = rng.uniform(-max_angle, max_angle, size=3)
    return _axis_rotation(2, yaw) @ _axis_rotation(1, pitch) @ _axis_rotation(0, roll)


def uniform_in_ball(rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
    """n points uniform inside a ball of ``radius`` centred at the origin."""
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    r = radius * rng.uniform(0.0, 1.0, size=n) ** (1.0 / 3.0)
    return direction * r[:, None]


# ----------------------------------------------------------------------------- projection
def project(points_in_world: np.ndarray, R_cam_from_world: np.ndarray, center: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Normalized coordinates (m, 2) and depths (m,) of x_cam = R (X - c) (eq:projectionEquation)."""
    X_cam = (points_in_world - center) @ R_cam_from_world.T
    depth = X_cam[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    return X_cam[:, :2] / safe[:, None], depth


def in_image(x: np.ndarray, depth: np.ndarray, focal: float, image_size: tuple[int, int],
             min_depth: float = 1e-6) -> np.ndarray:
    """Chirality (depth > 0) and inside the image (principal point at the centre)."""
    half_w, half_h = 0.5 * image_size[0] / focal, 0.5 * image_size[1] / focal
    return (depth > min_depth) & (np.abs(x[:, 0]) < half_w) & (np.abs(x[:, 1]) < half_h)


def normalized_to_pixels(x: np.ndarray, focal: float, image_size: tuple[int, int]) -> np.ndarray:
    """COLMAP pixel convention: the image spans [0, W] x [0, H], principal point at (W/2, H/2)."""
    return x * focal + 0.5 * np.asarray(image_size, dtype=float)


def add_pixel_noise(x: np.ndarray, noise_px: float, focal: float, rng: np.random.Generator,
                    model: str = "uniform") -> np.ndarray:
    """Noisy copy of normalized ``x`` (m, 2); see the module docstring for the models."""
    if model not in NOISE_MODELS:
        raise InputError(f"unknown noise model {model!r} (choose from {', '.join(NOISE_MODELS)})", field="noise_model")
    m = x.shape[0]
    if noise_px == 0:
        return x.copy()
    if model == "uniform":
        magnitude = rng.uniform(0.0, noise_px, size=m)
        angle = rng.uniform(0.0, 2.0 * np.pi, size=m)
        delta = magnitude[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    elif model == "gaussian":
        delta = rng.normal(0.0, noise_px, size=(m, 2))
    else:  # opengv
        delta = rng.uniform(-noise_px, noise_px, size=(m, 2))
    return x + delta / focal


# ----------------------------------------------------------------------------- scenes
def _point_sampler(scene: str, rng: np.random.Generator, center_j: np.ndarray,
                   scene_radius: float, plane_depth: float, extra: dict):
    """A function n -> (n, 3) candidate points for ``scene`` (scene parameters drawn once here)."""
    if scene in ("standard", "pure_rotation"):
        return lambda n: uniform_in_ball(rng, n, scene_radius)
    if scene == "planar":
        extra["plane_normal"], extra["plane_offset"] = np.array([0.0, 0.0, 1.0]), plane_depth

        def planar(n: int) -> np.ndarray:
            xy = rng.uniform(-scene_radius, scene_radius, size=(n, 2))
            return np.column_stack([xy, np.full(n, plane_depth)])
        return planar
    if scene == "holoplane":
        # plane through c_i = 0, c_j and (0, 0, 1): spanned by e_z and c_j's horizontal part.
        e_z = np.array([0.0, 0.0, 1.0])
        horizontal = center_j - center_j[2] * e_z
        if np.linalg.norm(horizontal) < 1e-3:
            raise _RedrawPose  # c_j on the optical axis: the plane is not defined
        v = horizontal / np.linalg.norm(horizontal)
        extra["plane_normal"], extra["plane_offset"] = np.cross(e_z, v), 0.0
        half_side = 0.5 * scene_radius  # square of side 20 m for the default 20 m radius

        def holoplane(n: int) -> np.ndarray:
            a = rng.uniform(0.0, 2.0 * half_side, size=n)  # along e_z (in front of camera i)
            b = rng.uniform(-half_side, half_side, size=n)
            return a[:, None] * e_z + b[:, None] * v
        return holoplane
    if scene == "rankregular_line":
        # random line in Z = plane_depth passing near camera i's optical axis so both views see it
        anchor = np.array([*rng.uniform(-0.2, 0.2, size=2) * plane_depth, plane_depth])
        phi = rng.uniform(0.0, np.pi)
        direction = np.array([np.cos(phi), np.sin(phi), 0.0])
        extra["line_point"], extra["line_direction"] = anchor, direction

        def line(n: int) -> np.ndarray:
            s = rng.uniform(-scene_radius, scene_radius, size=n)
            return anchor + s[:, None] * direction
        return line
    raise InputError(f"unknown scene {scene!r} (choose from {', '.join(SCENES)})", field="scene")


class _RedrawPose(Exception):
    pass


def simulate_twoview(scene: str = "standard", *, num_points: int = 1000, noise_px: float = 1.0,
                     focal: float = 800.0, image_size: tuple[int, int] | int = (960, 960),
                     rng: np.random.Generator | int | None = None, noise_model: str = "uniform",
                     max_parallax: float = 2.0, max_rotation: float = 0.5, scene_radius: float = 20.0,
                     plane_depth: float = 10.0) -> TwoViewProblem:
    """Draw one two-view problem of ``scene`` (module docstring). ``rng`` may be a seed."""
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r} (choose from {', '.join(SCENES)})", field="scene")
    if noise_model not in NOISE_MODELS:
        raise InputError(f"unknown noise model {noise_model!r}", field="noise_model")
    if num_points < 1:
        raise InputError("must be >= 1", field="num_points")
    if not (noise_px >= 0 and focal > 0):
        raise InputError("noise must be >= 0 and focal > 0", field="noise_px/focal")
    if isinstance(image_size, (int, np.integer)):
        image_size = (int(image_size), int(image_size))
    image_size = (int(image_size[0]), int(image_size[1]))
    seed = rng if isinstance(rng, (int, np.integer)) else None
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng

    for _ in range(_MAX_POSE_ATTEMPTS):
        R_j = bounded_rotation(rng, max_rotation).T  # OpenGV's rotation is cam->world
        center_j = np.zeros(3) if scene == "pure_rotation" else uniform_in_ball(rng, 1, max_parallax)[0]
        extra: dict = {}
        try:
            sample = _point_sampler(scene, rng, center_j, scene_radius, plane_depth, extra)
        except _RedrawPose:
            continue
        kept: list[np.ndarray] = []
        have = 0
        batch = max(4 * num_points, 1000)
        for _ in range(_MAX_POINT_BATCHES):
            X = sample(batch)
            x_i, d_i = project(X, np.eye(3), np.zeros(3))
            x_j, d_j = project(X, R_j, center_j)
            ok = in_image(x_i, d_i, focal, image_size) & in_image(x_j, d_j, focal, image_size)
            if np.any(ok):
                kept.append(X[ok])
                have += int(ok.sum())
            if have >= num_points:
                break
        if have < num_points:
            continue  # e.g. a line or holoplane that camera j barely sees: new pose
        points = np.concatenate(kept)[:num_points]
        x_i_true, _ = project(points, np.eye(3), np.zeros(3))
        x_j_true, _ = project(points, R_j, center_j)
        x_i = add_pixel_noise(x_i_true, noise_px, focal, rng, noise_model)
        x_j = add_pixel_noise(x_j_true, noise_px, focal, rng, noise_model)
        return TwoViewProblem(R_j_from_i=R_j, t_j_from_i=R_j @ (np.zeros(3) - center_j),
                              x_i=x_i, x_j=x_j, x_i_true=x_i_true, x_j_true=x_j_true,
                              points_in_i=points, center_j=center_j, scene=scene, focal=float(focal),
                              image_size=image_size, noise_px=float(noise_px), noise_model=noise_model,
                              seed=None if seed is None else int(seed), extra=extra)
    raise AlgorithmError(f"could not place {num_points} visible points in scene {scene!r} "
                         f"after {_MAX_POSE_ATTEMPTS} camera draws")


# ----------------------------------------------------------------------------- files
_ARRAY_FIELDS = ("R_j_from_i", "t_j_from_i", "x_i", "x_j", "x_i_true", "x_j_true", "points_in_i", "center_j")


def save_twoview(path: str | os.PathLike, problem: TwoViewProblem) -> Path:
    """Write ``problem`` (with its ground truth) as ``.npz``; atomic (temp file + rename)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {name: np.asarray(getattr(problem, name), dtype=float) for name in _ARRAY_FIELDS}
    arrays.update(
        format=np.array("rotonly-twoview-1"), scene=np.array(problem.scene), focal=np.array(problem.focal),
        image_size=np.array(problem.image_size, dtype=np.int64), noise_px=np.array(problem.noise_px),
        noise_model=np.array(problem.noise_model), seed=np.array(-1 if problem.seed is None else problem.seed),
    )
    for key, value in problem.extra.items():
        arrays[f"extra_{key}"] = np.asarray(value)
    with atomic.file_path(path, ".npz") as temporary:
        np.savez(temporary, **arrays)
    return path


def load_twoview(path: str | os.PathLike) -> TwoViewProblem:
    """Read a file written by :func:`save_twoview`; bad files raise :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is bad input
        raise InputError(f"not a .npz file ({exc})", path=path) from exc
    with data:
        if "format" not in data.files or str(data["format"]) != "rotonly-twoview-1":
            raise InputError("not a rotonly two-view simulation (missing 'format')", path=path, field="format")
        missing = [name for name in _ARRAY_FIELDS if name not in data.files]
        if missing:
            raise InputError(f"missing arrays {missing}", path=path, field=missing[0])
        arrays = {name: np.array(data[name], dtype=float) for name in _ARRAY_FIELDS}
        m = arrays["x_i"].shape[0]
        for name in ("x_i", "x_j", "x_i_true", "x_j_true"):
            if arrays[name].shape != (m, 2):
                raise InputError(f"expected shape ({m}, 2), got {arrays[name].shape}", path=path, field=name)
        if arrays["R_j_from_i"].shape != (3, 3):
            raise InputError("expected a 3x3 matrix", path=path, field="R_j_from_i")
        seed = int(data["seed"])
        extra = {key[len("extra_"):]: np.array(data[key]) for key in data.files if key.startswith("extra_")}
        return TwoViewProblem(**arrays, scene=str(data["scene"]), focal=float(data["focal"]),
                              image_size=tuple(int(v) for v in data["image_size"]),
                              noise_px=float(data["noise_px"]), noise_model=str(data["noise_model"]),
                              seed=None if seed < 0 else seed, extra=extra)
