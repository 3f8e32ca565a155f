"""Writing OpenMVG's ``sfm_data.json`` (formats.md §1): cereal's pretty JSON, byte for byte as
OpenMVG writes it; the structure (most of the file) is built as text, vectorised."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.geometry.tracks import ranks_within
from rotonly_cli.io import atomic
from rotonly_cli.io.openmvg.cameras import INTRINSIC_DISTORTION_FIELDS, check_model, distort_project, to_openmvg_pixels
from rotonly_cli.io.openmvg.sfm_data import CEREAL_MSB, CEREAL_POLY_PLAIN, UNDEFINED_INDEX
from rotonly_cli.scene.types import SfMScene, View

PathLike = str | os.PathLike


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
    pixels = to_openmvg_pixels(pixels[observation_order])
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


#: the structure text is made this many observations at a time (whole landmarks): all of it
#: at once held ~16 Python strings per observation and the text twice (str, then its bytes)
OBSERVATIONS_PER_PIECE = 1 << 16


def _structure_text(scene: SfMScene) -> str:
    """The ``structure`` array exactly as json.dumps(indent=4) writes it (at indent level 1)."""
    return "".join(_structure_pieces(scene))


def _structure_pieces(scene: SfMScene) -> Iterator[str]:
    """:func:`_structure_text` in consecutive pieces of whole landmarks, about
    OBSERVATIONS_PER_PIECE observations each."""
    flat = _flat_structure(scene)
    num_points = flat.point_ids.size
    if not num_points:
        yield "[]"
        return
    ends = np.cumsum(flat.track_lengths)
    start = 0
    while start < num_points:
        before = int(ends[start - 1]) if start else 0
        stop = min(max(int(np.searchsorted(ends, before + OBSERVATIONS_PER_PIECE, side="right")), start + 1),
                   num_points)
        yield _landmarks_text(flat, start, stop, before, int(ends[stop - 1]))
        start = stop


def _landmarks_text(flat: _FlatStructure, start: int, stop: int, first_obs: int, end_obs: int) -> str:
    """Landmarks [start, stop) of the ``structure`` array (observations [first_obs, end_obs)),
    with the array's opening before the first landmark and its closing after the last one,
    else a separating comma before: one join of literal texts and value texts (ids as
    integers, coordinates by :func:`_float_reprs`), no Python loop per landmark or
    observation. (str.join and one encode are ~2x faster than bytes.join over the pieces.)"""
    lengths = flat.track_lengths[start:stop]
    num_points = stop - start
    # Value slots: per landmark id, X (3), then per observation view, id_feat, x (2).
    num_values = 4 * num_points + 4 * (end_obs - first_obs)
    landmark_start = 4 * np.arange(num_points) + 4 * (np.cumsum(lengths) - lengths)
    observation_start = np.repeat(landmark_start + 4, lengths) + 4 * ranks_within(lengths)
    values = np.empty(num_values, dtype=object)
    values[landmark_start] = _integer_texts(flat.point_ids[start:stop])
    values[(landmark_start[:, None] + np.arange(1, 4)).reshape(-1)] = _float_reprs(flat.points[start:stop])
    values[(observation_start[:, None] + np.arange(2)).reshape(-1)] = \
        _integer_texts(flat.view_feature[first_obs:end_obs])
    values[(observation_start[:, None] + np.arange(2, 4)).reshape(-1)] = _float_reprs(flat.pixels[first_obs:end_obs])

    # texts[s] precedes value slot s; texts[-1] ends the piece.
    closing = np.empty(num_points, dtype=object)
    closing[:] = _CLOSE_NO_OBSERVATIONS
    closing[lengths > 0] = _CLOSE_OBSERVATIONS
    texts = np.empty(num_values + 1, dtype=object)
    texts[landmark_start[1:]] = closing[:-1] + (",\n" + _HEAD_TEXTS[0])
    texts[0] = ("[\n" if start == 0 else ",\n") + _HEAD_TEXTS[0]
    for offset in range(1, 4):
        texts[landmark_start + offset] = _HEAD_TEXTS[offset]
        texts[observation_start + offset] = _OBSERVATION_TEXTS[offset]
    texts[observation_start] = _NEXT_OBSERVATION
    texts[landmark_start[lengths > 0] + 4] = _OPEN_OBSERVATIONS
    texts[-1] = closing[-1] + (_indent(1) + "]" if stop == flat.point_ids.size else "")
    pieces = np.empty(2 * num_values + 1, dtype=object)
    pieces[0::2] = texts
    pieces[1::2] = values
    return "".join(pieces.tolist())


def sfm_data_document(scene: SfMScene, include_structure: bool = True) -> dict:
    """The cereal JSON document of ``scene`` (formats.md §1, writer rules §6.2)."""
    ptr_counter = 0  # one archive-wide shared_ptr counter: views, then intrinsics (§1.2)
    type_ids: dict[str, int] = {}  # polymorphic name -> k, archive-wide

    def next_ptr_id() -> int:
        nonlocal ptr_counter
        ptr_counter += 1
        return CEREAL_MSB | ptr_counter

    def polymorphic(name: str) -> dict:
        if name in type_ids:
            return {"polymorphic_id": type_ids[name]}
        type_ids[name] = len(type_ids) + 1
        return {"polymorphic_id": CEREAL_MSB | type_ids[name], "polymorphic_name": name}

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
            "polymorphic_id": CEREAL_POLY_PLAIN,
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
        focal, principal_point, distortion = check_model(intrinsic)
        data: dict[str, Any] = {
            "width": _json_uint(intrinsic.width, where + ".width"),
            "height": _json_uint(intrinsic.height, where + ".height"),
            "focal_length": _json_floats(focal, where + ".params"),
            "principal_point": _json_floats(to_openmvg_pixels(principal_point),
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


def _sfm_data_chunks(scene: SfMScene, include_structure: bool) -> Iterator[bytes]:
    """sfm_data.json in consecutive pieces: the structure array (most of the file) is
    built apart, a few landmarks at a time, and not copied into the small document."""
    document = sfm_data_document(scene, include_structure=False)
    text = json.dumps(document, indent=4, ensure_ascii=False, allow_nan=False)
    if not include_structure or scene.structure is None:
        yield text.encode("utf-8")
        return
    marker = '\n    "structure": [],\n'
    head, tail = text.split(marker)  # exactly one occurrence
    pieces = _structure_pieces(scene)
    first = next(pieces)  # validated before anything is written
    yield (head + '\n    "structure": ').encode("utf-8")
    yield first.encode("ascii")
    for piece in pieces:
        yield piece.encode("ascii")
    yield (",\n" + tail).encode("utf-8")


def sfm_data_bytes(scene: SfMScene, include_structure: bool = True) -> bytes:
    """Deterministic pretty JSON (4-space indent like cereal's rapidjson PrettyWriter)."""
    return b"".join(_sfm_data_chunks(scene, include_structure))


def write_sfm_data(path: PathLike, scene: SfMScene, include_structure: bool = True) -> None:
    """Write ``scene`` as an OpenMVG 2.1-loadable ``sfm_data.json`` (atomically)."""
    atomic.write_bytes(path, _sfm_data_chunks(scene, include_structure))
