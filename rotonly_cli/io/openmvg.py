"""OpenMVG 2.x files <-> rotonly dataclasses (formats.md §1-§2, pitfalls §6).

Readers and writers for ``sfm_data.json`` (cereal JSON), ``<stem>.feat``, ``matches.*.txt|bin``
and pairs files, the OpenMVG camera models (forward model and OpenMVG's own iterative
undistortion) and whole projects (``read_project`` / ``write_project``).

Pixel convention: OpenMVG puts the centre of the top-left pixel at (0, 0), rotonly (COLMAP) at
(0.5, 0.5). Keypoints, landmark observations ``x`` and the principal point get +0.5 when read
and -0.5 when written, here and nowhere else (architecture.md "Conventions").
"""

from __future__ import annotations

import json
import os
import struct
import warnings
from dataclasses import dataclass
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.scene.types import Intrinsics, PairMatches, Pose, SfMScene, Structure, View

PathLike = str | os.PathLike

UNDEFINED_INDEX = 0xFFFFFFFF  # OpenMVG UndefinedIndexT (formats.md §1.3)
PIXEL_OFFSET = 0.5  # COLMAP pixel = OpenMVG pixel + 0.5

# cereal polymorphism constants (formats.md §1.2)
_POLY_PLAIN = 0x40000000  # msb2_32bit: dynamic type == static type, no name follows
_MSB = 0x80000000  # msb_32bit: first occurrence of a name / of a pointed-to object

# OpenMVG intrinsic types we model: polymorphic name -> (distortion field, its length)
# (formats.md §1.4; [MVG] Camera_*_io.hpp).
INTRINSIC_DISTORTION_FIELDS: dict[str, tuple[str | None, int]] = {
    "pinhole": (None, 0),
    "pinhole_radial_k1": ("disto_k1", 1),
    "pinhole_radial_k3": ("disto_k3", 3),
    "pinhole_brown_t2": ("disto_t2", 5),
    "fisheye": ("fisheye", 4),
}

# Default match-file preference of read_project: (file name, config, verified).
_MATCH_FILE_PREFERENCE: tuple[tuple[str, str | None, bool], ...] = (
    ("matches.e.bin", "E", True),
    ("matches.e.txt", "E", True),
    ("matches.f.bin", "F", True),
    ("matches.f.txt", "F", True),
    ("matches.putative.bin", None, False),
    ("matches.putative.txt", None, False),
)

# image_describer.json as OpenMVG's ComputeFeatures writes it for SIFT (formats.md §2.1);
# SfM/ComputeMatches need it in the matches directory to know the regions type (SIFT_Regions
# -> SIOPointFeature, the 4-column .feat).
_IMAGE_DESCRIBER_JSON = {
    "image_describer": {
        "polymorphic_id": _MSB | 1,
        "polymorphic_name": "SIFT_Image_describer",
        "ptr_wrapper": {
            "valid": 1,
            "data": {
                "params": {
                    "first_octave": 0,
                    "num_octaves": 6,
                    "num_scales": 3,
                    "edge_threshold": 10.0,
                    "peak_threshold": 0.04,
                    "root_sift": True,
                },
                "bOrientation": True,
            },
        },
    },
    "regions_type": {
        "polymorphic_id": _MSB | 2,
        "polymorphic_name": "SIFT_Regions",
        "ptr_wrapper": {"valid": 1, "data": {"value0": [], "value1": []}},
    },
}


# ============================================================================ pixel convention

def _to_openmvg_pixels(pixels_colmap: np.ndarray) -> np.ndarray:
    """COLMAP -> OpenMVG pixel convention (-0.5), canonicalised so that a write->read->write
    cycle is byte-identical: ``q`` is iterated to a fixed point of q -> (q + 0.5) - 0.5, which
    floating point reaches after at most a couple of steps (only values whose +0.5 crosses a
    binade boundary move at all)."""
    q = np.asarray(pixels_colmap, dtype=np.float64) - PIXEL_OFFSET
    for _ in range(4):
        q_next = (q + PIXEL_OFFSET) - PIXEL_OFFSET
        if np.array_equal(q_next, q):
            break
        q = q_next
    return q


def _to_colmap_pixels(pixels_openmvg: np.ndarray) -> np.ndarray:
    return np.asarray(pixels_openmvg, dtype=np.float64) + PIXEL_OFFSET


# ============================================================================ camera models

def _check_model(intrinsics: Intrinsics) -> tuple[float, np.ndarray, np.ndarray]:
    """Return (focal, principal point (COLMAP convention), distortion) of an OpenMVG model."""
    if intrinsics.model not in INTRINSIC_DISTORTION_FIELDS:
        raise InputError(
            f"unsupported OpenMVG intrinsic type {intrinsics.model!r} "
            f"(known: {', '.join(INTRINSIC_DISTORTION_FIELDS)})",
            field=f"intrinsics[{intrinsics.id}].model")
    _, num_distortion = INTRINSIC_DISTORTION_FIELDS[intrinsics.model]
    params = np.asarray(intrinsics.params, dtype=np.float64).ravel()
    if params.size != 3 + num_distortion:
        raise InputError(
            f"{intrinsics.model} needs {3 + num_distortion} params [focal, ppx, ppy, k...], "
            f"got {params.size}", field=f"intrinsics[{intrinsics.id}].params")
    return float(params[0]), params[1:3], params[3:]


def _radial_disto_functor(k: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Squared distorted radius as a function of the squared undistorted one:
    r2 (1 + k1 r2 + k2 r2^2 + k3 r2^3)^2 ([MVG] Camera_Pinhole_Radial.cpp distoFunctor)."""
    poly = np.zeros_like(r2)
    for coefficient in k[::-1]:  # Horner: k1 + r2 (k2 + r2 k3)
        poly = coefficient + r2 * poly
    return r2 * np.square(1.0 + r2 * poly)


def _bisection_radius_solve(k: np.ndarray, r2_target: np.ndarray,
                            epsilon: float = 1e-10) -> np.ndarray:
    """Vectorised ``radial_distortion::bisection_Radius_Solve`` ([MVG] Camera_Pinhole_Radial.cpp):
    grow the bracket by factors of 1.05, then bisect until it is narrower than ``epsilon``.
    Each element follows exactly OpenMVG's scalar sequence (masked updates)."""
    lower = r2_target.copy()
    upper = r2_target.copy()
    for _ in range(2000):  # 1.05^2000 ~ 1e42: ample for any sane distortion
        shrink = _radial_disto_functor(k, lower) > r2_target
        if not shrink.any():
            break
        lower[shrink] /= 1.05
    for _ in range(2000):
        grow = _radial_disto_functor(k, upper) < r2_target
        if not grow.any():
            break
        upper[grow] *= 1.05
    for _ in range(200):  # each step halves the bracket: 200 steps cover any double range
        active = epsilon < upper - lower
        if not active.any():
            break
        mid = 0.5 * (lower + upper)
        above = _radial_disto_functor(k, mid) > r2_target
        upper = np.where(active & above, mid, upper)
        lower = np.where(active & ~above, mid, lower)
    return 0.5 * (lower + upper)


def _newton_polish_radius(k: np.ndarray, r2_target: np.ndarray,
                          r2_estimate: np.ndarray) -> np.ndarray:
    """Two Newton steps on OpenMVG's own equation D(s) = r2_target, started from its bisection
    result. The bisection stops at an *absolute* 1e-10 bracket on r^2, i.e. a relative error
    of ~1e-6 near the image centre (r ~ 0.01); the polish solves the same equation to machine
    precision and stays within OpenMVG's bracket. Steps that would not reduce the residual
    (non-monotone D) are not taken."""
    s = r2_estimate
    for _ in range(2):
        poly = np.zeros_like(s)  # P(s) = k1 + s k2 + s^2 k3 and its derivative
        poly_derivative = np.zeros_like(s)
        for coefficient in k[::-1]:
            poly_derivative = poly + s * poly_derivative
            poly = coefficient + s * poly
        factor = 1.0 + s * poly
        residual = s * factor * factor - r2_target
        derivative = factor * factor + 2.0 * s * factor * (poly + s * poly_derivative)
        with np.errstate(divide="ignore", invalid="ignore"):
            candidate = np.where(derivative > 0, s - residual / np.where(
                derivative > 0, derivative, 1.0), s)
        better = np.abs(_radial_disto_functor(k, candidate) - r2_target) <= np.abs(residual)
        s = np.where(better, candidate, s)
    return s


def _brown_displacement(k1: float, k2: float, k3: float, t1: float, t2: float,
                        points: np.ndarray) -> np.ndarray:
    """Brown-Conrady displacement (x_d - x) ([MVG] Camera_Pinhole_Brown.cpp distoFunction;
    t1 = OpenCV p1, t2 = OpenCV p2)."""
    x, y = points[:, 0], points[:, 1]
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    dx = x * radial + t2 * (r2 + 2.0 * x * x) + 2.0 * t1 * x * y
    dy = y * radial + t1 * (r2 + 2.0 * y * y) + 2.0 * t2 * x * y
    return np.stack([dx, dy], axis=1)


def add_distortion(model: str, distortion: np.ndarray, normalized: np.ndarray) -> np.ndarray:
    """OpenMVG ``add_disto`` on (n, 2) undistorted normalized coordinates."""
    points = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
    if model == "pinhole":
        return points.copy()
    if model in ("pinhole_radial_k1", "pinhole_radial_k3"):
        r2 = np.einsum("ij,ij->i", points, points)
        coefficient = np.ones_like(r2)
        r_power = np.ones_like(r2)
        for k in distortion:  # 1 + k1 r^2 + k2 r^4 + k3 r^6
            r_power = r_power * r2
            coefficient = coefficient + k * r_power
        return points * coefficient[:, None]
    if model == "pinhole_brown_t2":
        return points + _brown_displacement(*distortion, points)
    if model == "fisheye":
        # theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8), theta = atan(r); identity for
        # r <= 1e-8 ([MVG] Camera_Pinhole_Fisheye.cpp add_disto).
        r = np.hypot(points[:, 0], points[:, 1])
        theta = np.arctan(r)
        theta2 = theta * theta
        theta_d = theta * (1.0 + theta2 * (distortion[0] + theta2 * (
            distortion[1] + theta2 * (distortion[2] + theta2 * distortion[3]))))
        scale = np.ones_like(r)
        far = r > 1e-8
        scale[far] = theta_d[far] / r[far]
        return points * scale[:, None]
    raise InputError(f"unsupported OpenMVG intrinsic type {model!r}", field="model")


def remove_distortion(model: str, distortion: np.ndarray, distorted: np.ndarray) -> np.ndarray:
    """OpenMVG ``remove_disto`` on (n, 2) distorted normalized coordinates, with OpenMVG's own
    iterations: bisection on r^2 (radial, then polished to machine precision, see
    ``_newton_polish_radius``), fixed point on the displacement (Brown, stop at L1 residual
    <= 1e-10), exactly 10 fixed-point steps on theta (fisheye: like OpenMVG, not converged for
    strong distortion near the image border)."""
    points = np.asarray(distorted, dtype=np.float64).reshape(-1, 2)
    if model == "pinhole":
        return points.copy()
    if model in ("pinhole_radial_k1", "pinhole_radial_k3"):
        r2 = np.einsum("ij,ij->i", points, points)
        scale = np.ones_like(r2)
        nonzero = r2 != 0
        if nonzero.any():
            k = np.asarray(distortion, dtype=np.float64)
            r2_undistorted = _newton_polish_radius(
                k, r2[nonzero], _bisection_radius_solve(k, r2[nonzero]))
            scale[nonzero] = np.sqrt(r2_undistorted / r2[nonzero])
        return points * scale[:, None]
    if model == "pinhole_brown_t2":
        undistorted = points.copy()
        displacement = _brown_displacement(*distortion, undistorted)
        active = np.abs(undistorted + displacement - points).sum(axis=1) > 1e-10
        for _ in range(1000):  # OpenMVG loops unbounded; 1000 only guards divergence
            if not active.any():
                break
            undistorted[active] = points[active] - displacement[active]
            displacement[active] = _brown_displacement(*distortion, undistorted[active])
            active[active] = np.abs(undistorted[active] + displacement[active]
                                    - points[active]).sum(axis=1) > 1e-10
        return undistorted
    if model == "fisheye":
        theta_d = np.hypot(points[:, 0], points[:, 1])
        scale = np.ones_like(theta_d)
        far = theta_d > 1e-8
        if far.any():
            k1, k2, k3, k4 = distortion
            theta = theta_d[far].copy()
            for _ in range(10):  # exactly OpenMVG's 10 fixed-point steps
                theta2 = theta * theta
                theta = theta_d[far] / (1.0 + theta2 * (k1 + theta2 * (k2 + theta2 * (
                    k3 + theta2 * k4))))
            scale[far] = np.tan(theta) / theta_d[far]
        return points * scale[:, None]
    raise InputError(f"unsupported OpenMVG intrinsic type {model!r}", field="model")


def undistort_normalize(intrinsics: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(n, 2) pixels (COLMAP convention) -> (n, 2) undistorted normalized coordinates (z = 1),
    OpenMVG's ``remove_disto(ima2cam(p))``. The 0.5 pixel shifts of keypoints and principal
    point cancel, so this equals OpenMVG on its own pixels."""
    focal, principal_point, distortion = _check_model(intrinsics)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    distorted = (pixels - principal_point) / focal
    return remove_distortion(intrinsics.model, distortion, distorted)


def distort_project(intrinsics: Intrinsics, normalized: np.ndarray) -> np.ndarray:
    """(n, 2) undistorted normalized coordinates -> (n, 2) pixels (COLMAP convention),
    OpenMVG's forward model ``cam2ima(add_disto(x))``."""
    focal, principal_point, distortion = _check_model(intrinsics)
    distorted = add_distortion(intrinsics.model, distortion, normalized)
    return distorted * focal + principal_point


# ======================================================================== sfm_data.json: reading

class _JsonFields:
    """Typed access to a parsed JSON object; errors name the file and a field path."""

    def __init__(self, path: PathLike):
        self.path = str(path)

    def fail(self, where: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=where)

    def member(self, obj: Any, key: str, where: str) -> Any:
        if not isinstance(obj, dict):
            raise self.fail(where, f"expected a JSON object, got {type(obj).__name__}")
        if key not in obj:
            raise self.fail(f"{where}.{key}" if where else key, "missing field")
        return obj[key]

    def typed(self, obj: Any, key: str, where: str, kind: type, label: str) -> Any:
        value = self.member(obj, key, where)
        if not isinstance(value, kind):
            raise self.fail(f"{where}.{key}" if where else key, f"expected {label}, got {type(value).__name__}")
        return value

    def array(self, obj: Any, key: str, where: str) -> list:
        return self.typed(obj, key, where, list, "an array")

    def uint(self, obj: Any, key: str, where: str) -> int:
        # cereal reads unsigned fields with rapidjson GetUint(): JSON integers only (§1.2).
        value = self.member(obj, key, where)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFFFFFF:
            raise self.fail(f"{where}.{key}", f"expected an unsigned 32-bit integer, got {value!r}")
        return value

    def string(self, obj: Any, key: str, where: str) -> str:
        return self.typed(obj, key, where, str, "a string")

    def number(self, obj: Any, key: str, where: str) -> float:
        value = self.member(obj, key, where)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(f"{where}.{key}", f"expected a number, got {value!r}")
        return float(value)

    def numbers(self, obj: Any, key: str, where: str, length: int | None = None) -> np.ndarray:
        value = self.array(obj, key, where)
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise self.fail(f"{where}.{key}", "expected an array of numbers")
        if length is not None and len(value) != length:
            raise self.fail(f"{where}.{key}", f"expected {length} numbers, got {len(value)}")
        return np.array(value, dtype=np.float64)

    def map_items(self, obj: Any, key: str) -> list[tuple[int, Any, str]]:
        """A cereal map: array of {"key": k, "value": v} -> [(k, v, field path)]; read by key,
        never by position (formats.md §1.1: unordered_map order is arbitrary)."""
        items = []
        seen: set[int] = set()
        for position, item in enumerate(self.array(obj, key, "")):
            where = f"{key}[{position}]"
            item_key = self.uint(item, "key", where)
            if item_key in seen:
                raise self.fail(where + ".key", f"duplicate key {item_key}")
            seen.add(item_key)
            items.append((item_key, self.member(item, "value", where), f"{key}[key={item_key}]"))
        return items


class _PolymorphicReader:
    """cereal's archive-wide tables (formats.md §1.2): polymorphic id -> type name, and
    shared-pointer id -> object data, both filled in file order."""

    def __init__(self, fields: _JsonFields):
        self.fields = fields
        self.names: dict[int, str] = {}
        self.pointers: dict[int, Any] = {}

    def type_name(self, value: Any, where: str, plain_name: str) -> str:
        if isinstance(value, dict) and "polymorphic_id" not in value:
            return plain_name  # sfm_data_version < 0.3: non-polymorphic View
        poly_id = self.fields.uint(value, "polymorphic_id", where)
        if poly_id == _POLY_PLAIN:
            return plain_name
        if poly_id == 0:
            raise self.fields.fail(where + ".polymorphic_id", "null pointer")
        if poly_id & _MSB:
            name = self.fields.string(value, "polymorphic_name", where)
            self.names[poly_id & ~_MSB] = name
            return name
        if poly_id not in self.names:
            raise self.fields.fail(where + ".polymorphic_id",
                                   f"id {poly_id} refers to no earlier polymorphic_name")
        return self.names[poly_id]

    def data(self, value: Any, where: str) -> dict:
        wrapper = self.fields.member(value, "ptr_wrapper", where)
        ptr_id = self.fields.uint(wrapper, "id", where + ".ptr_wrapper")
        if ptr_id & _MSB:
            data = self.fields.member(wrapper, "data", where + ".ptr_wrapper")
            if not isinstance(data, dict):
                raise self.fields.fail(where + ".ptr_wrapper.data", "expected a JSON object")
            self.pointers[ptr_id & ~_MSB] = data
            return data
        if ptr_id not in self.pointers:  # a repeated shared_ptr: {"id": n} only
            raise self.fields.fail(where + ".ptr_wrapper.id",
                                   f"id {ptr_id} refers to no earlier object")
        return self.pointers[ptr_id]


def _load_json(path: PathLike) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=str(path))
    try:
        with open(path, "rb") as handle:
            return json.loads(handle.read())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"malformed JSON ({error})", path=str(path)) from None


def _read_intrinsic(fields: _JsonFields, intrinsic_id: int, model: str, data: dict,
                    where: str) -> Intrinsics:
    if model not in INTRINSIC_DISTORTION_FIELDS:
        raise fields.fail(where + ".polymorphic_name",
                          f"unsupported intrinsic type {model!r} "
                          f"(supported: {', '.join(INTRINSIC_DISTORTION_FIELDS)})")
    where_data = where + ".ptr_wrapper.data"
    width = fields.uint(data, "width", where_data)
    height = fields.uint(data, "height", where_data)
    focal = fields.number(data, "focal_length", where_data)
    principal_point = fields.numbers(data, "principal_point", where_data, 2)
    distortion_field, num_distortion = INTRINSIC_DISTORTION_FIELDS[model]
    distortion = (fields.numbers(data, distortion_field, where_data, num_distortion)
                  if distortion_field else np.zeros(0))
    params = np.concatenate([[focal], _to_colmap_pixels(principal_point), distortion])
    return Intrinsics(intrinsic_id, model, width, height, params)


def read_sfm_data(path: PathLike) -> SfMScene:
    """Read an OpenMVG ``sfm_data.json`` (any version 0.1-0.3) into an SfMScene.

    Poses are keyed by *view* id (a pose shared by several views is copied to each);
    ``View.pose_id`` keeps OpenMVG's pose id. Control points are not read.
    """
    fields = _JsonFields(path)
    document = _load_json(path)
    if not isinstance(document, dict):
        raise fields.fail("", "expected a JSON object at the top level")
    fields.string(document, "sfm_data_version", "")
    scene = SfMScene(root_path=fields.string(document, "root_path", ""), source="openmvg")
    poly = _PolymorphicReader(fields)

    for view_key, value, where in fields.map_items(document, "views"):
        poly.type_name(value, where, "View")  # View or view_priors: same leading fields
        data = poly.data(value, where)
        where_data = where + ".ptr_wrapper.data"
        local_path = fields.string(data, "local_path", where_data)
        filename = fields.string(data, "filename", where_data)
        view_id = fields.uint(data, "id_view", where_data)
        if view_id != view_key:
            raise fields.fail(where_data + ".id_view", f"{view_id} differs from the map key")
        scene.views[view_id] = View(
            id=view_id,
            name=f"{local_path.rstrip('/')}/{filename}" if local_path else filename,
            intrinsics_id=fields.uint(data, "id_intrinsic", where_data),
            pose_id=fields.uint(data, "id_pose", where_data),
            width=fields.uint(data, "width", where_data),
            height=fields.uint(data, "height", where_data),
        )

    for intrinsic_id, value, where in fields.map_items(document, "intrinsics"):
        model = poly.type_name(value, where, "IntrinsicBase")
        data = poly.data(value, where)
        scene.intrinsics[intrinsic_id] = _read_intrinsic(fields, intrinsic_id, model, data, where)

    poses_by_pose_id: dict[int, Pose] = {}
    for pose_id, value, where in fields.map_items(document, "extrinsics"):
        rotation = fields.array(value, "rotation", where)
        if len(rotation) != 3 or not all(isinstance(row, list) and len(row) == 3
                                         for row in rotation):
            raise fields.fail(where + ".rotation", "expected 3 rows of 3 numbers")
        try:
            R_cam_from_world = np.array(rotation, dtype=np.float64)  # row-major (§1.5)
        except (TypeError, ValueError):
            raise fields.fail(where + ".rotation", "expected numbers") from None
        center = fields.numbers(value, "center", where, 3)
        poses_by_pose_id[pose_id] = Pose(R_cam_from_world, center)
    for view in scene.views.values():
        pose = poses_by_pose_id.get(view.pose_id)
        if pose is not None:
            scene.poses[view.id] = Pose(pose.R_cam_from_world.copy(), pose.center.copy())

    landmarks = fields.map_items(document, "structure")
    if landmarks:
        point_ids = np.empty(len(landmarks), dtype=np.int64)
        points = np.empty((len(landmarks), 3))
        observations: list[list[tuple[int, int]]] = []
        observation_pixels: list[np.ndarray] = []
        for index, (point_id, value, where) in enumerate(landmarks):
            point_ids[index] = point_id
            points[index] = fields.numbers(value, "X", where, 3)
            track: list[tuple[int, int]] = []
            pixels = []
            for view_id, observation, where_obs in fields.map_items(value, "observations"):
                where_obs = f"{where}.{where_obs}"
                track.append((view_id, fields.uint(observation, "id_feat", where_obs)))
                pixels.append(fields.numbers(observation, "x", where_obs, 2))
            observations.append(track)
            observation_pixels.append(_to_colmap_pixels(np.array(pixels).reshape(-1, 2)))
        scene.structure = Structure(point_ids, points, None, observations, observation_pixels)
    return scene


# ======================================================================== sfm_data.json: writing

def _json_uint(value: Any, where: str) -> int:
    integer = int(value)
    if integer != value or not 0 <= integer <= 0xFFFFFFFF:
        raise InputError(f"not an unsigned 32-bit integer: {value!r}", field=where)
    return integer


def _json_floats(values: np.ndarray, where: str) -> list:
    """Finite doubles as nested Python lists; json writes them as shortest round-trip
    decimals, like rapidjson's PrettyWriter (§1.2)."""
    array = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise InputError("non-finite value cannot be written to OpenMVG JSON", field=where)
    return array.tolist()


def _effective_pose_id(view: View, has_pose: bool) -> int:
    """OpenMVG ``id_pose``: ``None`` -> the view id (as SfMInit_ImageListing assigns it); an
    undefined id stays undefined unless the scene holds a pose for the view."""
    if view.pose_id is None or (view.pose_id == UNDEFINED_INDEX and has_pose):
        return view.id
    return view.pose_id


def _view_size(scene: SfMScene, view: View) -> tuple[int, int]:
    if view.width is not None and view.height is not None:
        return view.width, view.height
    intrinsic = scene.intrinsics.get(view.intrinsics_id)
    if intrinsic is None:
        return 0, 0
    return intrinsic.width, intrinsic.height


@dataclass
class _FlatStructure:
    """Landmarks in document order (point id ascending, observations by view id), as flat
    arrays: ``track_lengths`` (N,), ``view_feature`` (M, 2), ``pixels`` (M, 2) in OpenMVG's
    pixel convention."""

    point_ids: np.ndarray
    points: np.ndarray
    track_lengths: np.ndarray
    view_feature: np.ndarray
    pixels: np.ndarray


def _landmark_pixels(scene: SfMScene, point_of_observation: np.ndarray,
                     view_feature: np.ndarray) -> np.ndarray:
    """(M, 2) pixel (COLMAP convention) of each observation, computed per view: the view's
    keypoint, else the projection of the point through the view's camera (stored landmark
    pixels are used by the caller before this)."""
    structure = scene.structure
    assert structure is not None
    pixels = np.empty((len(view_feature), 2))
    view_ids, feature_ids = view_feature[:, 0], view_feature[:, 1]
    by_view = np.argsort(view_ids, kind="stable")  # observations grouped by view
    unique_views, group_start = np.unique(view_ids[by_view], return_index=True)
    group_end = np.append(group_start[1:], len(by_view))
    for view_id, start, end in zip(unique_views.tolist(), group_start.tolist(), group_end.tolist()):
        rows = by_view[start:end]
        keypoints = scene.keypoints.get(view_id)
        if keypoints is not None:
            keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
            has_keypoint = (feature_ids[rows] >= 0) & (feature_ids[rows] < len(keypoints))
            pixels[rows[has_keypoint]] = keypoints[feature_ids[rows[has_keypoint]]]
            rows = rows[~has_keypoint]
        if not rows.size:
            continue
        pose, view = scene.poses.get(view_id), scene.views.get(view_id)
        intrinsic = None if view is None else scene.intrinsics.get(view.intrinsics_id)
        if pose is None or intrinsic is None:
            point_index = int(point_of_observation[rows[0]])
            raise InputError(f"no pixel position for observation (view {view_id}, feature "
                             f"{int(feature_ids[rows[0]])})", field=f"structure[{point_index}]")
        # x_cam = R (X - c)  (architecture.md "Conventions")
        points_in_camera = (np.asarray(structure.points, dtype=np.float64)[point_of_observation[rows]]
                            - np.asarray(pose.center, dtype=np.float64).reshape(1, 3)
                            ) @ np.asarray(pose.R_cam_from_world, dtype=np.float64).T
        pixels[rows] = distort_project(intrinsic, points_in_camera[:, :2] / points_in_camera[:, 2:3])
    return pixels


def _flat_structure(scene: SfMScene) -> _FlatStructure:
    """Landmarks ready for the writer, validated, with vectorised sorting and pixel
    conversion (no Python loop per landmark)."""
    structure = scene.structure
    assert structure is not None
    point_ids = np.asarray(structure.point_ids, dtype=np.int64).reshape(-1)
    if point_ids.size and (point_ids.min() < 0 or point_ids.max() > 0xFFFFFFFF):
        raise InputError("point id outside uint32", field="structure.point_ids")
    if len(np.unique(point_ids)) != point_ids.size:
        raise InputError("duplicate point id", field="structure.point_ids")
    track_lengths, view_feature = structure.flat_observations()
    if len(track_lengths) != point_ids.size:
        raise InputError("one observation list per point expected", field="structure.observations")
    if view_feature.size and (view_feature.min() < 0 or view_feature.max() > 0xFFFFFFFF):
        raise InputError("view id or id_feat outside uint32", field="structure.observations")
    point_of_observation = np.repeat(np.arange(point_ids.size), track_lengths)
    pixels = structure.flat_observation_pixels(track_lengths)
    if pixels is None:
        pixels = _landmark_pixels(scene, point_of_observation, view_feature)

    # Document order: points by id, each track by view id (both sorts stable).
    point_order = np.argsort(point_ids, kind="stable")
    rank_of_point = np.empty_like(point_order)
    rank_of_point[point_order] = np.arange(point_order.size)
    observation_order = np.lexsort((view_feature[:, 0], rank_of_point[point_of_observation]))
    sorted_points = rank_of_point[point_of_observation][observation_order]
    sorted_views = view_feature[observation_order, 0]
    repeated = (sorted_points[1:] == sorted_points[:-1]) & (sorted_views[1:] == sorted_views[:-1])
    if np.any(repeated):
        point_index = point_order[sorted_points[np.flatnonzero(repeated)[0]]]
        raise InputError("two observations in one view (OpenMVG keys them by view)",
                         field=f"structure[{int(point_ids[point_index])}]")
    points = np.asarray(structure.points, dtype=np.float64).reshape(-1, 3)[point_order]
    pixels = _to_openmvg_pixels(pixels[observation_order])
    if not np.all(np.isfinite(points)):
        raise InputError("non-finite value cannot be written to OpenMVG JSON", field="structure.X")
    if not np.all(np.isfinite(pixels)):
        raise InputError("non-finite value cannot be written to OpenMVG JSON", field="structure.x")
    return _FlatStructure(point_ids[point_order], points, track_lengths[point_order],
                          view_feature[observation_order], pixels)


def _structure_rows(scene: SfMScene) -> list[tuple[int, list, list, list]]:
    """Landmarks as Python values, sorted by point id: (point id, X, [(view, id_feat)] sorted
    by view, [x in OpenMVG pixels]) (for :func:`sfm_data_document`)."""
    flat = _flat_structure(scene)
    ends = np.cumsum(flat.track_lengths).tolist()
    starts = [0] + ends[:-1]
    tracks = [tuple(pair) for pair in flat.view_feature.tolist()]
    pixels = flat.pixels.tolist()
    return [(point_id, point, tracks[start:end], pixels[start:end]) for point_id, point, start, end
            in zip(flat.point_ids.tolist(), flat.points.tolist(), starts, ends)]


# Text templates reproducing json.dumps(indent=4) for landmarks, ~10x faster than the
# pure-Python indenting encoder; test_io_openmvg checks both give the same bytes.
def _indent(level: int) -> str:
    return "\n" + " " * (4 * level)


_OBSERVATION_TEMPLATE = (
    " " * 20 + "{" + _indent(6) + '"key": %s,' + _indent(6) + '"value": {' + _indent(7)
    + '"id_feat": %s,' + _indent(7) + '"x": [' + _indent(8) + "%s," + _indent(8) + "%s"
    + _indent(7) + "]" + _indent(6) + "}" + _indent(5) + "}")
_LANDMARK_HEAD = (
    " " * 8 + "{" + _indent(3) + '"key": %s,' + _indent(3) + '"value": {' + _indent(4)
    + '"X": [' + _indent(5) + "%s," + _indent(5) + "%s," + _indent(5) + "%s" + _indent(4)
    + "],")
_LANDMARK_TAIL = _indent(3) + "}" + _indent(2) + "}"


# Literal text between the values of one landmark / one observation (the templates split at
# their placeholders): _LANDMARK_HEAD = H0 id H1 X0 H2 X1 H3 X2 H4, an observation
# = B0 view B1 id_feat B2 x0 B3 x1 B4.
_HEAD_TEXTS = _LANDMARK_HEAD.split("%s")
_OBSERVATION_TEXTS = _OBSERVATION_TEMPLATE.split("%s")
_OPEN_OBSERVATIONS = _HEAD_TEXTS[4] + _indent(4) + '"observations": [\n' + _OBSERVATION_TEXTS[0]
_NEXT_OBSERVATION = _OBSERVATION_TEXTS[4] + ",\n" + _OBSERVATION_TEXTS[0]
_CLOSE_OBSERVATIONS = _OBSERVATION_TEXTS[4] + _indent(4) + "]" + _LANDMARK_TAIL
_CLOSE_NO_OBSERVATIONS = _HEAD_TEXTS[4] + _indent(4) + '"observations": []' + _LANDMARK_TAIL


def _integer_texts(values: np.ndarray) -> list[str]:
    """``str`` of every int64."""
    return list(map(str, np.ascontiguousarray(values, dtype=np.int64).reshape(-1).tolist()))


def _float_reprs(values: np.ndarray) -> list[str]:
    """``repr`` of every float64 (Python's shortest round-trip form, what json writes)."""
    return list(map(repr, np.ascontiguousarray(values, dtype=np.float64).reshape(-1).tolist()))


def _structure_text(scene: SfMScene) -> str:
    """The ``structure`` array exactly as json.dumps(indent=4) writes it (at indent level
    1), as one join of literal texts and value texts (ids as integers, coordinates by
    :func:`_float_reprs`): no Python loop per landmark or observation. (str.join and one
    encode are ~2x faster than bytes.join over the ~10⁶ pieces.)"""
    flat = _flat_structure(scene)
    num_points = flat.point_ids.size
    if not num_points:
        return "[]"
    lengths = flat.track_lengths
    # Value slots: per landmark id, X (3), then per observation view, id_feat, x (2).
    num_values = 4 * num_points + 4 * len(flat.view_feature)
    landmark_start = 4 * np.arange(num_points) + 4 * (np.cumsum(lengths) - lengths)
    observation_start = np.repeat(landmark_start + 4, lengths) + 4 * _rank_within_track(lengths)
    values = np.empty(num_values, dtype=object)
    values[landmark_start] = _integer_texts(flat.point_ids)
    values[(landmark_start[:, None] + np.arange(1, 4)).reshape(-1)] = _float_reprs(flat.points)
    values[(observation_start[:, None] + np.arange(2)).reshape(-1)] = _integer_texts(flat.view_feature)
    values[(observation_start[:, None] + np.arange(2, 4)).reshape(-1)] = _float_reprs(flat.pixels)

    # texts[s] precedes value slot s; texts[-1] ends the array.
    closing = np.empty(num_points, dtype=object)
    closing[:] = _CLOSE_NO_OBSERVATIONS
    closing[lengths > 0] = _CLOSE_OBSERVATIONS
    texts = np.empty(num_values + 1, dtype=object)
    texts[landmark_start[1:]] = closing[:-1] + (",\n" + _HEAD_TEXTS[0])
    texts[0] = "[\n" + _HEAD_TEXTS[0]
    for offset in range(1, 4):
        texts[landmark_start + offset] = _HEAD_TEXTS[offset]
        texts[observation_start + offset] = _OBSERVATION_TEXTS[offset]
    texts[observation_start] = _NEXT_OBSERVATION
    texts[landmark_start[lengths > 0] + 4] = _OPEN_OBSERVATIONS
    texts[-1] = closing[-1] + _indent(1) + "]"
    pieces = np.empty(2 * num_values + 1, dtype=object)
    pieces[0::2] = texts
    pieces[1::2] = values
    return "".join(pieces.tolist())


def _rank_within_track(track_lengths: np.ndarray) -> np.ndarray:
    """0, 1, ..., k-1 for every track of length k, concatenated."""
    total = int(track_lengths.sum())
    track_starts = np.repeat(np.cumsum(track_lengths) - track_lengths, track_lengths)
    return np.arange(total) - track_starts


def sfm_data_document(scene: SfMScene, include_structure: bool = True) -> dict:
    """The cereal JSON document of ``scene`` (formats.md §1, writer rules §6.2)."""
    ptr_counter = 0  # one archive-wide shared_ptr counter: views, then intrinsics (§1.2)
    type_ids: dict[str, int] = {}  # polymorphic name -> k, archive-wide

    def next_ptr_id() -> int:
        nonlocal ptr_counter
        ptr_counter += 1
        return _MSB | ptr_counter

    def polymorphic(name: str) -> dict:
        if name in type_ids:
            return {"polymorphic_id": type_ids[name]}
        type_ids[name] = len(type_ids) + 1
        return {"polymorphic_id": _MSB | type_ids[name], "polymorphic_name": name}

    views_json = []
    pose_view_ids: dict[int, int] = {}  # pose id -> first view (by id) that carries it
    for view_id in sorted(scene.views):
        view = scene.views[view_id]
        where = f"views[{view_id}]"
        local_path, _, filename = view.name.replace("\\", "/").rpartition("/")
        width, height = _view_size(scene, view)
        pose_id = _effective_pose_id(view, view_id in scene.poses)
        if view_id in scene.poses:
            pose_view_ids.setdefault(pose_id, view_id)
        views_json.append({"key": _json_uint(view_id, where), "value": {
            "polymorphic_id": _POLY_PLAIN,
            "ptr_wrapper": {"id": next_ptr_id(), "data": {
                "local_path": local_path,
                "filename": filename,
                "width": _json_uint(width, where + ".width"),
                "height": _json_uint(height, where + ".height"),
                "id_view": _json_uint(view_id, where),
                "id_intrinsic": _json_uint(view.intrinsics_id, where + ".intrinsics_id"),
                "id_pose": _json_uint(pose_id, where + ".pose_id"),
            }}}})

    intrinsics_json = []
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = scene.intrinsics[intrinsic_id]
        where = f"intrinsics[{intrinsic_id}]"
        focal, principal_point, distortion = _check_model(intrinsic)
        data: dict[str, Any] = {
            "width": _json_uint(intrinsic.width, where + ".width"),
            "height": _json_uint(intrinsic.height, where + ".height"),
            "focal_length": _json_floats(focal, where + ".params"),
            "principal_point": _json_floats(_to_openmvg_pixels(principal_point),
                                            where + ".params"),
        }
        distortion_field, _ = INTRINSIC_DISTORTION_FIELDS[intrinsic.model]
        if distortion_field:
            data[distortion_field] = _json_floats(distortion, where + ".params")
        intrinsics_json.append({"key": _json_uint(intrinsic_id, where), "value": {
            **polymorphic(intrinsic.model),
            "ptr_wrapper": {"id": next_ptr_id(), "data": data}}})

    # Every written pose is referenced by a view (OpenMVG's ValidIds, §1.9).
    extrinsics_json = []
    for pose_id in sorted(pose_view_ids):
        pose = scene.poses[pose_view_ids[pose_id]]
        where = f"poses[{pose_view_ids[pose_id]}]"
        extrinsics_json.append({"key": _json_uint(pose_id, where), "value": {
            "rotation": _json_floats(np.asarray(pose.R_cam_from_world).reshape(3, 3), where),
            "center": _json_floats(np.asarray(pose.center).reshape(3), where)}})

    structure_json = []
    if include_structure and scene.structure is not None:
        for point_id, point, track, pixels in _structure_rows(scene):
            structure_json.append({"key": point_id, "value": {
                "X": point,
                "observations": [{"key": view_id, "value": {"id_feat": feature_index,
                                                            "x": pixel}}
                                 for (view_id, feature_index), pixel in zip(track, pixels)]}})

    return {
        "sfm_data_version": "0.3",
        "root_path": scene.root_path,
        "views": views_json,
        "intrinsics": intrinsics_json,
        "extrinsics": extrinsics_json,
        "structure": structure_json,
        "control_points": [],
    }


def _sfm_data_chunks(scene: SfMScene, include_structure: bool) -> list[bytes]:
    """sfm_data.json in consecutive pieces: the structure array (most of the file) is
    built apart and not copied into the small document."""
    document = sfm_data_document(scene, include_structure=False)
    text = json.dumps(document, indent=4, ensure_ascii=False, allow_nan=False)
    if not include_structure or scene.structure is None:
        return [text.encode("utf-8")]
    marker = '\n    "structure": [],\n'
    head, tail = text.split(marker)  # exactly one occurrence
    return [(head + '\n    "structure": ').encode("utf-8"), _structure_text(scene).encode("ascii"),
            (",\n" + tail).encode("utf-8")]


def sfm_data_bytes(scene: SfMScene, include_structure: bool = True) -> bytes:
    """Deterministic pretty JSON (4-space indent like cereal's rapidjson PrettyWriter)."""
    return b"".join(_sfm_data_chunks(scene, include_structure))


def write_sfm_data(path: PathLike, scene: SfMScene, include_structure: bool = True) -> None:
    """Write ``scene`` as an OpenMVG 2.1-loadable ``sfm_data.json`` (atomically)."""
    atomic.write_bytes(path, _sfm_data_chunks(scene, include_structure))


# ============================================================================ .feat files

def _read_bytes(path: PathLike) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=str(path))
    return path.read_bytes()


def _tokens_per_line(payload: bytes) -> tuple[np.ndarray, int]:
    """Number of whitespace-separated tokens on each line (vectorised over the bytes), and
    the total token count."""
    data = np.frombuffer(payload, dtype=np.uint8)
    if data.size == 0:
        return np.zeros(0, dtype=np.int64), 0
    whitespace = (data == 32) | (data == 9) | (data == 13) | (data == 10) | (data == 11) | (
        data == 12)
    token_start = ~whitespace
    token_start[1:] &= whitespace[:-1]
    starts = np.flatnonzero(token_start)
    newlines = np.flatnonzero(data == 10)
    line_of_token = np.searchsorted(newlines, starts)
    counts = np.bincount(line_of_token, minlength=newlines.size + 1)
    return counts, starts.size


def read_feature_table(path: PathLike) -> np.ndarray:
    """(n, 4) ``x y scale orientation`` rows of a ``.feat`` file, x/y still in OpenMVG's
    pixel convention (formats.md §2.2). Blank lines are ignored; every other line must have
    exactly 4 columns (line index = feature index = ``id_feat``)."""
    payload = _read_bytes(path)
    counts, num_tokens = _tokens_per_line(payload)
    bad_lines = np.flatnonzero((counts != 4) & (counts != 0))
    if bad_lines.size:
        line = int(bad_lines[0])
        raise InputError(f"{int(counts[line])} columns, expected 4 "
                         "(x y scale orientation)", path=str(path), field=f"line {line + 1}")
    if num_tokens == 0:
        return np.zeros((0, 4))
    # np.fromstring(sep=" ") is numpy's C text-to-double parser (about 3x faster than
    # np.array(bytes.split(), float)); any whitespace separates. A bad token raises (numpy 2)
    # or stops the parse early (older numpy: DeprecationWarning), hence the size check.
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            values = np.fromstring(payload.decode("ascii", errors="replace"), dtype=np.float64,
                                   sep=" ")
    except ValueError:
        values = np.zeros(0)
    if values.size != num_tokens or not np.all(np.isfinite(values)):
        raise InputError("non-numeric or non-finite value", path=str(path))
    return values.reshape(-1, 4)


def read_features(path: PathLike) -> np.ndarray:
    """(n, 2) keypoint pixels of a ``.feat`` file, in COLMAP's pixel convention (+0.5)."""
    return _to_colmap_pixels(read_feature_table(path)[:, :2])


def write_features(path: PathLike, pixels: np.ndarray,
                   scales_orientations: np.ndarray | None = None) -> None:
    """Write a ``.feat`` file from (n, 2) COLMAP-convention pixels (-0.5 on the way out).
    Without ``scales_orientations`` each row gets scale 1 and orientation 0, as OpenMVG's own
    external-features demo writes."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    table = np.empty((pixels.shape[0], 4))
    table[:, :2] = _to_openmvg_pixels(pixels)
    if scales_orientations is None:
        table[:, 2], table[:, 3] = 1.0, 0.0
    else:
        table[:, 2:] = np.asarray(scales_orientations, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(table)):
        raise InputError("non-finite keypoint", path=str(path))
    # Lossless and compact: values that are float32 numbers (every keypoint that came from a
    # detector or a COLMAP database, scale 1, orientation 0) keep %.9g, which is exact for
    # float32; others (e.g. re-projected through a converted camera model) get %.12g:
    # 8 decimals on a 4-digit pixel, 1e-8 px, far below the 1e-9 normalized-coordinate
    # round-trip bound (1.4e-6 px at f = 1380), and stable under write -> read -> write.
    # OpenMVG parses either into its float32 features.
    exact32 = table.astype(np.float32).astype(np.float64) == table
    columns = []
    for c in range(4):
        col = np.empty(table.shape[0], dtype=object)
        for mask, fmt in ((exact32[:, c], "%.9g"), (~exact32[:, c], "%.12g")):
            if np.any(mask):
                values = table[mask, c]
                col[mask] = ((fmt + "\n") * values.shape[0] % tuple(values.tolist())).splitlines()
        columns.append(col)
    text = "".join(f"{a} {b} {c} {d}\n" for a, b, c, d in zip(*columns))
    atomic.write_bytes(path, text.encode("ascii"))


# ============================================================================ matches

MatchesDict = dict[tuple[int, int], np.ndarray]


def _add_pair(matches: MatchesDict, view_i: int, view_j: int, pair_matches: np.ndarray,
              path: PathLike, where: str) -> None:
    """Store with key (min, max) and columns swapped accordingly (types.py convention)."""
    if view_i == view_j:
        raise InputError(f"pair ({view_i}, {view_j}) matches a view with itself",
                         path=str(path), field=where)
    if view_i > view_j:
        view_i, view_j, pair_matches = view_j, view_i, pair_matches[:, ::-1]
    if (view_i, view_j) in matches:
        raise InputError(f"pair ({view_i}, {view_j}) appears twice", path=str(path), field=where)
    matches[(view_i, view_j)] = np.ascontiguousarray(pair_matches, dtype=np.int64)


def _read_matches_bin(path: PathLike) -> MatchesDict:
    """cereal PortableBinary PairWiseMatches (formats.md §2.5): u8 endianness flag, u64
    n_pairs, then per pair u32 I, u32 J, u64 n, n x (u32 i, u32 j)."""
    payload = _read_bytes(path)
    if len(payload) < 9:
        raise InputError(f"truncated: {len(payload)} bytes, header needs 9", path=str(path),
                         field="header")
    if payload[0] != 1:
        raise InputError(f"endianness flag {payload[0]} is not 1 (little-endian)",
                         path=str(path), field="header")
    (num_pairs,) = struct.unpack_from("<Q", payload, 1)
    offset = 9
    matches: MatchesDict = {}
    pair_header = struct.Struct("<IIQ")
    for pair_index in range(num_pairs):
        where = f"pair {pair_index}"
        if offset + pair_header.size > len(payload):
            raise InputError(f"truncated: header of pair {pair_index} of {num_pairs} is missing "
                             f"(byte {offset} of {len(payload)})", path=str(path), field=where)
        view_i, view_j, num_matches = pair_header.unpack_from(payload, offset)
        offset += pair_header.size
        end = offset + 8 * num_matches
        if end > len(payload):
            raise InputError(f"truncated: pair ({view_i}, {view_j}) announces {num_matches} "
                             f"matches, only {(len(payload) - offset) // 8} present",
                             path=str(path), field=where)
        pair_matches = np.frombuffer(payload, dtype="<u4", count=2 * num_matches,
                                     offset=offset).reshape(-1, 2)
        offset = end
        _add_pair(matches, view_i, view_j, pair_matches, path, where)
    if offset != len(payload):
        raise InputError(f"{len(payload) - offset} unexpected bytes after {num_pairs} pairs",
                         path=str(path), field="trailer")
    return matches


def _read_matches_txt(path: PathLike) -> MatchesDict:
    """Text matches (formats.md §2.4): ``I J`` / ``N`` / N lines ``i j``, repeated."""
    payload = _read_bytes(path)
    text = payload.decode("ascii", errors="replace")
    tokens = text.split()
    try:
        values = np.array(tokens, dtype=np.int64)
    except ValueError:
        raise InputError("non-integer token", path=str(path)) from None
    if np.any(values < 0) or np.any(values > 0xFFFFFFFF):
        raise InputError("negative or > 32-bit index", path=str(path))
    matches: MatchesDict = {}
    position = 0
    pair_index = 0
    while position < values.size:
        where = f"pair {pair_index}"
        if position + 3 > values.size:
            raise InputError("truncated pair header (expected 'I J' then 'N')", path=str(path),
                             field=where)
        view_i, view_j, num_matches = (int(v) for v in values[position:position + 3])
        position += 3
        if position + 2 * num_matches > values.size:
            raise InputError(f"truncated: pair ({view_i}, {view_j}) announces {num_matches} "
                             "matches", path=str(path), field=where)
        block = values[position:position + 2 * num_matches].reshape(-1, 2)
        position += 2 * num_matches
        _add_pair(matches, view_i, view_j, block, path, where)
        pair_index += 1
    return matches


def read_matches(path: PathLike) -> MatchesDict:
    """``matches.*.bin`` (cereal binary) or ``matches.*.txt`` -> {(i, j): (m, 2) int64}, i < j."""
    if str(path).endswith(".bin"):
        return _read_matches_bin(path)
    return _read_matches_txt(path)


def _sorted_match_arrays(
        matches: Mapping[tuple[int, int], Any]) -> list[tuple[int, int, np.ndarray]]:
    rows = []
    for (view_i, view_j), value in matches.items():
        array = value.matches if isinstance(value, PairMatches) else value
        array = np.asarray(array, dtype=np.int64).reshape(-1, 2)
        if np.any(array < 0) or np.any(array > 0xFFFFFFFF):
            raise InputError(f"pair ({view_i}, {view_j}): index outside uint32",
                             field="matches")
        rows.append((int(view_i), int(view_j), array))
    rows.sort(key=lambda row: (row[0], row[1]))  # std::map<Pair,...> order (§2.4)
    return rows


def matches_bytes(matches: Mapping[tuple[int, int], Any], binary: bool) -> bytes:
    rows = _sorted_match_arrays(matches)
    if binary:
        chunks = [struct.pack("<BQ", 1, len(rows))]
        for view_i, view_j, array in rows:
            chunks.append(struct.pack("<IIQ", view_i, view_j, array.shape[0]))
            chunks.append(array.astype("<u4").tobytes())
        return b"".join(chunks)
    chunks_text = []
    for view_i, view_j, array in rows:
        chunks_text.append(f"{view_i} {view_j}\n{array.shape[0]}\n")
        chunks_text.append(("%d %d\n" * array.shape[0]) % tuple(array.ravel().tolist()))
    return "".join(chunks_text).encode("ascii")


def write_matches(path: PathLike, matches: Mapping[tuple[int, int], Any]) -> None:
    """Write {(i, j): (m, 2)} (or PairMatches values) as ``.bin`` (cereal) or text."""
    atomic.write_bytes(path, matches_bytes(matches, binary=str(path).endswith(".bin")))


def read_pairs(path: PathLike, num_views: int | None = None) -> list[tuple[int, int]]:
    """Pairs file (formats.md §2.6: always text, adjacency lines ``I J1 J2 ...``) -> sorted
    unique (min, max) pairs; rejects I == J and, given ``num_views``, ids >= num_views."""
    text = _read_bytes(path).decode("ascii", errors="replace")
    pairs: set[tuple[int, int]] = set()
    for line_number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) < 2:
            raise InputError("expected 'I J1 J2 ...'", path=str(path), field=f"line {line_number}")
        try:
            ids = [int(token) for token in tokens]
        except ValueError:
            raise InputError("non-integer view id", path=str(path),
                             field=f"line {line_number}") from None
        for other in ids[1:]:
            if other == ids[0] or min(ids[0], other) < 0 or (
                    num_views is not None and max(ids[0], other) >= num_views):
                raise InputError(f"invalid pair ({ids[0]}, {other})", path=str(path),
                                 field=f"line {line_number}")
            pairs.add((min(ids[0], other), max(ids[0], other)))
    return sorted(pairs)


def write_pairs(path: PathLike, pairs: Iterable[tuple[int, int]]) -> None:
    """Text ``I J`` lines, sorted (what OpenMVG's savePairs writes, even for ``pairs.bin``)."""
    ordered = sorted({(min(int(i), int(j)), max(int(i), int(j))) for i, j in pairs})
    atomic.write_bytes(path, "".join(f"{i} {j}\n" for i, j in ordered).encode("ascii"))


# ============================================================================ projects

def _feature_stem(view: View) -> str:
    """OpenMVG names features ``basename_part(image path)`` (extension stripped, §2.2)."""
    return Path(view.name.replace("\\", "/")).stem


def _match_file_kind(name: str) -> tuple[str | None, bool]:
    """(PairMatches.config, verified) from an OpenMVG match file name."""
    for _, kind in (("e", "E"), ("f", "F"), ("h", "H")):
        if f".{kind.lower()}." in name:
            return kind, True
    if "putative" in name:
        return None, False
    return None, True


def _choose_match_file(matches_dir: Path, matches_file: PathLike | None) -> Path | None:
    if matches_file is not None:
        candidate = Path(matches_file)
        if not candidate.is_file() and not candidate.is_absolute():
            candidate = matches_dir / candidate
        if not candidate.is_file():
            raise InputError("matches file not found", path=str(candidate))
        return candidate
    for name, _, _ in _MATCH_FILE_PREFERENCE:
        if (matches_dir / name).is_file():
            return matches_dir / name
    return None


def read_project(sfm_data_path: PathLike, matches_dir: PathLike | None = None,
                 matches_file: PathLike | None = None) -> SfMScene:
    """sfm_data.json + ``<stem>.feat`` per view (keypoints + normalized) + matches.

    ``matches_dir`` defaults to the folder of ``matches_file`` if given, else of the
    sfm_data file. Without ``matches_file`` the first of matches.e.bin/.txt, matches.f.*,
    matches.putative.* is used (e/f -> verified, config "E"/"F"; putative -> unverified).
    """
    scene = read_sfm_data(sfm_data_path)
    if matches_dir is None:
        matches_dir = (Path(matches_file).parent if matches_file is not None
                       and Path(matches_file).is_file() else Path(sfm_data_path).parent)
    matches_dir = Path(matches_dir)
    if not matches_dir.is_dir():
        raise InputError("matches directory not found", path=str(matches_dir))

    stems: dict[str, int] = {}
    for view_id in sorted(scene.views):
        view = scene.views[view_id]
        stem = _feature_stem(view)
        if stem in stems:
            raise InputError(f"views {stems[stem]} and {view_id} share the feature file "
                             f"{stem}.feat", path=str(sfm_data_path), field="views")
        stems[stem] = view_id
        keypoints = read_features(matches_dir / f"{stem}.feat")
        scene.keypoints[view_id] = keypoints
        intrinsic = scene.intrinsics.get(view.intrinsics_id)
        if intrinsic is not None:  # undefined intrinsic: no calibration, no normalized
            scene.normalized[view_id] = undistort_normalize(intrinsic, keypoints)

    match_path = _choose_match_file(matches_dir, matches_file)
    if match_path is None:
        return scene
    config, verified = _match_file_kind(match_path.name)
    for (view_i, view_j), pair_matches in read_matches(match_path).items():
        where = f"pair ({view_i}, {view_j})"
        for view_id, column in ((view_i, 0), (view_j, 1)):
            if view_id not in scene.views:
                raise InputError(f"view {view_id} is not in sfm_data", path=str(match_path),
                                 field=where)
            if pair_matches.size and pair_matches[:, column].max() >= len(
                    scene.keypoints[view_id]):
                raise InputError(f"feature index {int(pair_matches[:, column].max())} >= "
                                 f"{len(scene.keypoints[view_id])} keypoints of view {view_id}",
                                 path=str(match_path), field=where)
        scene.pairs[(view_i, view_j)] = PairMatches(view_i, view_j, pair_matches, config=config,
                                                    verified=verified)
    return scene


def write_project(out_dir: PathLike, scene: SfMScene, include_structure: bool = True) -> None:
    """Write an OpenMVG project: sfm_data.json, ``<stem>.feat`` per view (empty if the view
    has no keypoints), image_describer.json (SfM/ComputeMatches need it, §2.1),
    matches.e.bin (verified pairs) and matches.putative.bin (unverified pairs, if any).

    Files are staged in a temporary folder beside ``out_dir``; a new ``out_dir`` appears by
    one rename, an existing one receives the files one rename each.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stems: dict[str, int] = {}
    for view_id in sorted(scene.views):
        stem = _feature_stem(scene.views[view_id])
        if stem in stems:
            raise InputError(f"views {stems[stem]} and {view_id} share the feature file "
                             f"{stem}.feat", field="views")
        stems[stem] = view_id
    with atomic.filling_dir(out_dir) as staging:
        write_sfm_data(staging / "sfm_data.json", scene, include_structure)
        for stem, view_id in stems.items():
            write_features(staging / f"{stem}.feat",
                           scene.keypoints.get(view_id, np.zeros((0, 2))))
        describer = json.dumps(_IMAGE_DESCRIBER_JSON, indent=4).encode("utf-8")
        atomic.write_bytes(staging / "image_describer.json", describer)
        verified = {key: pair for key, pair in scene.pairs.items() if pair.verified}
        unverified = {key: pair for key, pair in scene.pairs.items() if not pair.verified}
        if verified or not unverified:
            write_matches(staging / "matches.e.bin", verified)
        if unverified:
            write_matches(staging / "matches.putative.bin", unverified)
