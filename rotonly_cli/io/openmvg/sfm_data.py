"""Reading OpenMVG's ``sfm_data.json`` (cereal JSON, formats.md §1): a tolerant reader that
names the file and the field of every error."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io.inputs import Oversized, check_camera, load_json
from rotonly_cli.io.openmvg.cameras import INTRINSIC_DISTORTION_FIELDS, to_colmap_pixels
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, Structure, View

PathLike = str | os.PathLike


UNDEFINED_INDEX = 0xFFFFFFFF  # OpenMVG UndefinedIndexT (formats.md §1.3)

# cereal polymorphism constants (formats.md §1.2)
CEREAL_POLY_PLAIN = 0x40000000  # msb2_32bit: dynamic type == static type, no name follows
CEREAL_MSB = 0x80000000  # msb_32bit: first occurrence of a name / of a pointed-to object


# ======================================================================== sfm_data.json: reading

def _shown(value: Any) -> str:
    """``repr(value)``, cut to a readable length for error messages."""
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:45]}... ({len(text)} characters)"


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
            got = _shown(value) if isinstance(value, Oversized) else type(value).__name__
            raise self.fail(f"{where}.{key}" if where else key, f"expected {label}, got {got}")
        return value

    def array(self, obj: Any, key: str, where: str) -> list:
        return self.typed(obj, key, where, list, "an array")

    def uint(self, obj: Any, key: str, where: str) -> int:
        # cereal reads unsigned fields with rapidjson GetUint(): JSON integers only (§1.2).
        value = self.member(obj, key, where)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFFFFFF:
            raise self.fail(f"{where}.{key}", f"expected an unsigned 32-bit integer, got {_shown(value)}")
        return value

    def string(self, obj: Any, key: str, where: str) -> str:
        return self.typed(obj, key, where, str, "a string")

    def number(self, obj: Any, key: str, where: str) -> float:
        """A finite JSON number (cereal writes no NaN or infinity)."""
        value = self.member(obj, key, where)
        field = f"{where}.{key}" if where else key
        if type(value) not in (int, float):  # bool, str, null, Oversized ...
            raise self.fail(field, f"expected a number, got {_shown(value)}")
        if not np.isfinite(float(value)):
            raise self.fail(field, f"{value!r} is not a finite number")
        return float(value)

    def numbers(self, obj: Any, key: str, where: str, length: int | None = None) -> np.ndarray:
        """An array of finite JSON numbers (of ``length`` if given)."""
        return self.number_list(self.member(obj, key, where), f"{where}.{key}" if where else key, length)

    def number_list(self, value: Any, field: str, length: int | None = None) -> np.ndarray:
        if not isinstance(value, list):
            raise self.fail(field, f"expected an array, got {type(value).__name__}")
        if length is not None and len(value) != length:
            raise self.fail(field, f"expected {length} numbers, got {len(value)}")
        for k, v in enumerate(value):
            if type(v) not in (int, float):  # bool, str, null, Oversized ...
                raise self.fail(f"{field}[{k}]", f"expected a number, got {_shown(v)}")
        array = np.array(value, dtype=np.float64)
        if not np.all(np.isfinite(array)):
            k = int(np.flatnonzero(~np.isfinite(array))[0])
            raise self.fail(f"{field}[{k}]", f"{value[k]!r} is not a finite number")
        return array

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
        if poly_id == CEREAL_POLY_PLAIN:
            return plain_name
        if poly_id == 0:
            raise self.fields.fail(where + ".polymorphic_id", "null pointer")
        if poly_id & CEREAL_MSB:
            name = self.fields.string(value, "polymorphic_name", where)
            self.names[poly_id & ~CEREAL_MSB] = name
            return name
        if poly_id not in self.names:
            raise self.fields.fail(where + ".polymorphic_id",
                                   f"id {poly_id} refers to no earlier polymorphic_name")
        return self.names[poly_id]

    def data(self, value: Any, where: str) -> dict:
        wrapper = self.fields.member(value, "ptr_wrapper", where)
        ptr_id = self.fields.uint(wrapper, "id", where + ".ptr_wrapper")
        if ptr_id & CEREAL_MSB:
            data = self.fields.member(wrapper, "data", where + ".ptr_wrapper")
            if not isinstance(data, dict):
                raise self.fields.fail(where + ".ptr_wrapper.data", "expected a JSON object")
            self.pointers[ptr_id & ~CEREAL_MSB] = data
            return data
        if ptr_id not in self.pointers:  # a repeated shared_ptr: {"id": n} only
            raise self.fields.fail(where + ".ptr_wrapper.id",
                                   f"id {ptr_id} refers to no earlier object")
        return self.pointers[ptr_id]


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
    params = np.concatenate([[focal], to_colmap_pixels(principal_point), distortion])
    check_camera(fields.path, where_data, width, height, [focal], principal_point, params)
    return Intrinsics(intrinsic_id, model, width, height, params)


def _is_rotation(R: np.ndarray, tolerance: float = 1e-3) -> bool:
    """Orthonormal with determinant +1 up to ``tolerance`` (OpenMVG writes them to ~1e-15)."""
    return bool(np.abs(R @ R.T - np.eye(3)).max() < tolerance and np.linalg.det(R) > 0)


def read_sfm_data(path: PathLike, poses_only: bool = False) -> SfMScene:
    """Read an OpenMVG ``sfm_data.json`` (any version 0.1-0.3) into an SfMScene.

    Poses are keyed by *view* id (a pose shared by several views is copied to each);
    ``View.pose_id`` keeps OpenMVG's pose id. Control points are not read. ``poses_only``:
    views, intrinsics and poses; the structure is skipped unparsed (what an evaluation reads).
    """
    fields = _JsonFields(path)
    document = load_json(path, skip_member="structure" if poses_only else None)
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
        for size in ("width", "height"):
            if getattr(scene.views[view_id], size) == 0:
                raise fields.fail(f"{where_data}.{size}", "0: an image size must be > 0")

    for intrinsic_id, value, where in fields.map_items(document, "intrinsics"):
        model = poly.type_name(value, where, "IntrinsicBase")
        data = poly.data(value, where)
        scene.intrinsics[intrinsic_id] = _read_intrinsic(fields, intrinsic_id, model, data, where)

    poses_by_pose_id: dict[int, Pose] = {}
    for pose_id, value, where in fields.map_items(document, "extrinsics"):
        rotation = fields.array(value, "rotation", where)
        if len(rotation) != 3:
            raise fields.fail(where + ".rotation", "expected 3 rows of 3 numbers")
        R_cam_from_world = np.stack([fields.number_list(row, f"{where}.rotation[{r}]", 3)
                                     for r, row in enumerate(rotation)])  # row-major (§1.5)
        if not _is_rotation(R_cam_from_world):
            raise fields.fail(where + ".rotation", "not a rotation matrix (R Rᵀ = I, det R = 1)")
        center = fields.numbers(value, "center", where, 3)
        poses_by_pose_id[pose_id] = Pose(R_cam_from_world, center)
    for view in scene.views.values():
        pose = poses_by_pose_id.get(view.pose_id)
        if pose is not None:
            scene.poses[view.id] = Pose(pose.R_cam_from_world.copy(), pose.center.copy())

    landmarks = [] if poses_only else fields.map_items(document, "structure")
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
            observation_pixels.append(to_colmap_pixels(np.array(pixels).reshape(-1, 2)))
        scene.structure = Structure(point_ids, points, None, observations, observation_pixels)
    return scene
