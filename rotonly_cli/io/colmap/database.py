"""COLMAP databases (SQLite, formats.md §4.1–§4.5), read and written through pycolmap."""

from __future__ import annotations

import contextlib
import logging
import os
import sqlite3
import tempfile
from collections.abc import Iterator
from contextlib import closing, contextmanager, nullcontext
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError, write_error
from rotonly_cli.io import atomic
from rotonly_cli.io.colmap.cameras import import_pycolmap, normalize_keypoints, pycolmap_camera, to_colmap_intrinsics
from rotonly_cli.io.colmap.database_check import check_database, check_sqlite_file, snapshot_database
from rotonly_cli.io.inputs import check_finite
from rotonly_cli.scene.types import Intrinsics, PairMatches, SfMScene, View

PathLike = str | os.PathLike
logger = logging.getLogger(__name__)


# OpenMVG PairMatches.config -> COLMAP TwoViewGeometry config name (formats.md §4.5). A
# verified pair of unknown kind is written CALIBRATED: COLMAP skips UNDEFINED pairs.
_CONFIG_FROM_OPENMVG = {"E": "CALIBRATED", "F": "UNCALIBRATED", "H": "PLANAR", None: "CALIBRATED"}
# Verified-and-rejected configurations: not a usable pair.
_REJECTED_CONFIGS = ("UNDEFINED", "DEGENERATE", "WATERMARK")
# COLMAP 3.8's tables (its src/base/database.cc; data_fixtures/colmap38_herzjesu4 has them as
# COLMAP 3.8 wrote them) and the columns write_database copies into them from pycolmap's.
_COLMAP38_TABLES = (
    "CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL, "
    "width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL)",
    "CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE, "
    "camera_id INTEGER NOT NULL, prior_qw REAL, prior_qx REAL, prior_qy REAL, prior_qz REAL, prior_tx REAL, "
    "prior_ty REAL, prior_tz REAL, CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647), "
    "FOREIGN KEY(camera_id) REFERENCES cameras(camera_id))",
    "CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, "
    "data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE)",
    "CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, "
    "data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE)",
    "CREATE TABLE matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, "
    "data BLOB)",
    "CREATE TABLE two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, "
    "cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB)",
    "CREATE UNIQUE INDEX index_name ON images(name)",
)
_COLMAP38_COLUMNS = {
    "cameras": "camera_id, model, width, height, params, prior_focal_length", "images": "image_id, name, camera_id",
    "keypoints": "image_id, rows, cols, data", "descriptors": "image_id, rows, cols, data",
    "matches": "pair_id, rows, cols, data",
    "two_view_geometries": "pair_id, rows, cols, data, config, F, E, H, qvec, tvec",
}


# ============================================================================ database: reading

@contextmanager
def _open_database_copy(path: Path, scratch_dir: PathLike | None = None) -> Iterator:
    """pycolmap Database on a private copy of ``path`` (pycolmap's ``Database.open`` writes to
    the file it opens; the input stays byte-identical) in ``scratch_dir`` (default: a
    temporary folder), removed when the block ends. The copy is a consistent state of the
    input although another process may be writing it (:func:`snapshot_database`), and it is
    the copy that is checked (:func:`check_database`): what pycolmap reads is what was checked."""
    pycolmap = import_pycolmap()
    with (contextlib.nullcontext(scratch_dir) if scratch_dir is not None
          else tempfile.TemporaryDirectory(prefix="rotonly-db-")) as scratch:
        copy = Path(scratch) / "database.db"
        copies = [copy, Path(f"{copy}-wal"), Path(f"{copy}-shm"), Path(f"{copy}-journal")]
        try:
            try:
                snapshot_database(path, copy, shown=path)
            except OSError as exc:
                raise write_error(exc, scratch, field=None) from None
            check_database(copy, shown=path, is_input=False)
            try:
                database = pycolmap.Database.open(str(copy))
            except Exception:  # noqa: BLE001 - the copy passed check_database: the disk, not the input
                error = atomic.unreported_write_error(scratch, "pycolmap cannot open the database copy")
                raise write_error(error, scratch, field=None) from None
            try:
                yield database
            finally:
                database.close()
        finally:
            for leftover in copies:
                leftover.unlink(missing_ok=True)


def read_database(path: PathLike, include_unverified: bool = True, scratch_dir: PathLike | None = None) -> SfMScene:
    """COLMAP database -> SfMScene (formats.md §4.1-§4.6).

    Verified pairs come from ``two_view_geometries`` (inlier matches, config name and, when
    stored, ``cam2_from_cam1`` as R_j_from_i / unit t_j_from_i); pairs verified and rejected
    (UNDEFINED, DEGENERATE, WATERMARK or no inlier) are dropped; with
    ``include_unverified`` the raw ``matches`` of pairs never verified come with
    ``verified=False``. The database is read from a private copy in ``scratch_dir`` (default:
    a temporary folder), a consistent state of it although another process may be writing
    it, checked first (:func:`check_database`: nothing is read that pycolmap would refuse).
    ``path`` may also be an open ``pycolmap.Database`` (read in place).
    """
    pycolmap = import_pycolmap()
    if isinstance(path, pycolmap.Database):
        opened, path = nullcontext(path), Path("<pycolmap.Database>")
    else:
        path = check_sqlite_file(path)
        opened = _open_database_copy(path, scratch_dir)
    scene = SfMScene(source="colmap-db")
    with opened as database:
        cameras = {camera.camera_id: camera for camera in database.read_all_cameras()}
        for camera_id, camera in cameras.items():
            scene.intrinsics[camera_id] = Intrinsics(
                camera_id, camera.model.name, int(camera.width), int(camera.height),
                np.array(camera.params, dtype=np.float64), prior_focal=bool(camera.has_prior_focal_length))
        for image in database.read_all_images():
            image_id = int(image.image_id)
            if image.camera_id not in cameras:
                raise InputError(f"image {image_id} refers to missing camera {image.camera_id}",
                                 path=str(path), field="images")
            camera = cameras[image.camera_id]
            scene.views[image_id] = View(image_id, image.name, int(image.camera_id),
                                         width=int(camera.width), height=int(camera.height))
            if database.exists_keypoints(image_id):
                keypoints = np.asarray(database.read_keypoints(image_id))[:, :2]
            else:
                keypoints = np.zeros((0, 2))
            check_finite(keypoints, path, f"keypoints of image {image_id}", "keypoint")
            scene.keypoints[image_id] = keypoints.astype(np.float64)
            scene.normalized[image_id] = normalize_keypoints(camera, scene.keypoints[image_id])

        # one pair at a time: the whole table as pycolmap objects (and the raw matches of every
        # pair, read to skip the verified ones) held 16 more bytes per match at once
        verified_pair_ids = set()
        num_rejected = 0
        for pair_id in database.read_two_view_geometry_num_inliers()[0]:
            verified_pair_ids.add(int(pair_id))
            i, j = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))  # i < j, canonical
            geometry = database.read_two_view_geometry(i, j)
            config = pycolmap.TwoViewGeometryConfiguration(int(geometry.config)).name
            inliers = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            if config in _REJECTED_CONFIGS or inliers.shape[0] == 0:
                num_rejected += 1
                continue
            _check_match_indices(scene, i, j, inliers, path, "two_view_geometries")
            pair = PairMatches(i, j, inliers, config=config, verified=True)
            relative = geometry.cam2_from_cam1
            if relative is not None:
                pair.R_j_from_i = np.array(relative.rotation.matrix(), dtype=np.float64)
                if not np.all(np.isfinite(pair.R_j_from_i)):
                    raise InputError("qvec is not a rotation", path=str(path),
                                     field=f"two_view_geometries of pair ({i}, {j})")
                # A direction (scale unknown, §4.5): PLANAR/H decompositions store |t| != 1.
                translation = np.array(relative.translation, dtype=np.float64)
                norm = np.linalg.norm(translation)
                pair.t_j_from_i = translation / norm if norm > 0 else translation
            scene.pairs[(i, j)] = pair
        if num_rejected:
            logger.info("%s: %d verified-and-rejected pairs skipped", path, num_rejected)

        if include_unverified:
            for pair_id in database.read_num_matches()[0]:
                if int(pair_id) in verified_pair_ids:
                    continue
                i, j = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))
                matches = np.asarray(database.read_matches(i, j), dtype=np.int64).reshape(-1, 2)
                if matches.shape[0] == 0:
                    continue
                _check_match_indices(scene, i, j, matches, path, "matches")
                scene.pairs[(i, j)] = PairMatches(i, j, matches, verified=False)
    scene.pairs = dict(sorted(scene.pairs.items()))
    return scene


def _check_match_indices(scene: SfMScene, i: int, j: int, matches: np.ndarray, path: Path,
                         table: str) -> None:
    for view_id, column in ((i, 0), (j, 1)):
        if view_id not in scene.views:
            raise InputError(f"pair ({i}, {j}) refers to missing image {view_id}",
                             path=str(path), field=table)
        if matches.shape[0] and (matches[:, column].max() >= len(scene.keypoints[view_id])):
            raise InputError(f"pair ({i}, {j}): keypoint index {int(matches[:, column].max())} "
                             f">= {len(scene.keypoints[view_id])} keypoints of image {view_id}",
                             path=str(path), field=table)


# ============================================================================ database: writing

def id_offset(ids) -> int:
    """COLMAP ids must be > 0 (formats.md §4.2): shift a 0-based id set by +1."""
    ids = list(ids)
    return 1 - min(ids) if ids and min(ids) < 1 else 0


def write_database(path: PathLike, scene: SfMScene) -> None:
    """SfMScene -> new COLMAP database at ``path`` (replaced atomically), in COLMAP 3.8's
    layout (:func:`to_colmap38_layout`), which COLMAP 3.x opens and COLMAP / pycolmap 4.x
    migrate on opening.

    One camera per intrinsic (OpenMVG models mapped by ``to_colmap_intrinsics``), keypoints,
    ``matches`` for every pair and a ``two_view_geometries`` row (inliers = the pair's matches,
    config, ``cam2_from_cam1`` when known) for verified pairs. View/camera ids < 1 are
    shifted (``id_offset``).
    """
    pycolmap = import_pycolmap()
    path = Path(path)
    view_offset = id_offset(scene.views)
    camera_offset = id_offset(scene.intrinsics)
    with atomic.file_path(path, ".db", create=False, sidecars=("-journal", "-wal", "-shm")) as staging:
        database = pycolmap.Database.open(str(staging))
        try:
            _fill_database(pycolmap, database, scene, view_offset, camera_offset)
        finally:
            database.close()
        # pycolmap leaves the file in WAL mode, where every later reader (even read-only)
        # creates -wal/-shm files beside it; a rollback-journal file is self-contained.
        connection = sqlite3.connect(str(staging))
        try:
            connection.execute("PRAGMA journal_mode=DELETE")
        finally:
            connection.close()
        to_colmap38_layout(staging)


def to_colmap38_layout(path: PathLike) -> None:
    """Rewrite a database pycolmap 4.x wrote in COLMAP 3.8's layout: the tables of 3.8 (no
    rigs, frames or pose priors: pycolmap 4.x makes trivial ones when it opens the file, as
    for any 3.x database; image pose priors empty, descriptor type dropped) with the same
    rows. COLMAP 3.8 refuses 4.x's layout ("SQL logic error")."""
    path = Path(path)
    rebuilt = path.with_name(f"{path.name}.colmap38")
    try:
        with closing(sqlite3.connect(str(rebuilt))) as database:
            for statement in _COLMAP38_TABLES:
                database.execute(statement)
            database.execute("ATTACH DATABASE ? AS old", (str(path),))
            for table, columns in _COLMAP38_COLUMNS.items():
                database.execute(f"INSERT INTO main.{table} ({columns}) SELECT {columns} FROM old.{table}")
            database.commit()
            database.execute("DETACH DATABASE old")
        os.replace(rebuilt, path)
    finally:
        rebuilt.unlink(missing_ok=True)


def _fill_database(pycolmap, database, scene: SfMScene, view_offset: int,
                   camera_offset: int) -> None:
    camera_ids: dict[int, int] = {}
    for intrinsic_id in sorted(scene.intrinsics):
        intrinsic = to_colmap_intrinsics(scene.intrinsics[intrinsic_id])
        camera = pycolmap_camera(intrinsic, intrinsic_id + camera_offset)
        # calibrated unless the scene says the focal is a guess: COLMAP then keeps E-based geometry
        camera.has_prior_focal_length = intrinsic.prior_focal is not False
        camera_ids[intrinsic_id] = database.write_camera(camera, use_camera_id=True)
    # a view without intrinsic (OpenMVG's listing found no EXIF focal): COLMAP's no-EXIF
    # default, one camera per image size (§4.4; calibration.guess_missing_cameras)
    from rotonly_cli.io.cameras import guessed_cameras_per_size

    guesses, guessed_of_view = guessed_cameras_per_size(
        [scene.views[v] for v in sorted(scene.views) if scene.views[v].intrinsics_id not in camera_ids],
        max(camera_ids.values(), default=0) + 1, openmvg=False)
    for camera_id, guess in guesses.items():
        camera = pycolmap_camera(guess, camera_id)
        camera.has_prior_focal_length = False
        database.write_camera(camera, use_camera_id=True)
    camera_of_view = {**{v: camera_ids[view.intrinsics_id] for v, view in scene.views.items()
                         if view.intrinsics_id in camera_ids}, **guessed_of_view}
    for camera_id in sorted(set(camera_of_view.values())):
        rig = pycolmap.Rig(rig_id=camera_id)
        rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id))
        database.write_rig(rig, use_rig_id=True)
    for view_id in sorted(scene.views):
        view = scene.views[view_id]
        image_id = view_id + view_offset
        camera_id = camera_of_view[view_id]
        image = pycolmap.Image(name=view.name, camera_id=camera_id, image_id=image_id)
        database.write_image(image, use_image_id=True)
        frame = pycolmap.Frame(frame_id=image_id, rig_id=camera_id)
        frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA,
                                                             camera_id), image_id))
        database.write_frame(frame, use_frame_id=True)
        keypoints = scene.keypoints.get(view_id)
        if keypoints is not None:
            database.write_keypoints(image_id, np.ascontiguousarray(keypoints, dtype=np.float32)
                                     .reshape(-1, 2))
    for (i, j), pair in sorted(scene.pairs.items()):
        if i not in scene.views or j not in scene.views:
            raise InputError(f"pair ({i}, {j}) refers to a missing view", field="pairs")
        matches = np.ascontiguousarray(pair.matches, dtype=np.uint32).reshape(-1, 2)
        id1, id2 = i + view_offset, j + view_offset
        database.write_matches(id1, id2, matches)  # i < j: stored as given (§4.3)
        if not pair.verified:
            continue
        geometry = pycolmap.TwoViewGeometry()
        config = _CONFIG_FROM_OPENMVG.get(pair.config, pair.config)
        if config not in pycolmap.TwoViewGeometryConfiguration.__members__:
            raise InputError(f"unknown two-view configuration {pair.config!r}",
                             field=f"pairs[({i}, {j})].config")
        geometry.config = pycolmap.TwoViewGeometryConfiguration.__members__[config]
        geometry.inlier_matches = matches
        if pair.R_j_from_i is not None:
            translation = (np.zeros(3) if pair.t_j_from_i is None
                           else np.asarray(pair.t_j_from_i, dtype=np.float64).reshape(3))
            geometry.cam2_from_cam1 = pycolmap.Rigid3d(
                pycolmap.Rotation3d(np.asarray(pair.R_j_from_i, dtype=np.float64)), translation)
        database.write_two_view_geometry(id1, id2, geometry)


# ============================================================================ view-graph calibration

def write_fundamental_database(path: PathLike, scene: SfMScene, fundamentals: dict[tuple[int, int], np.ndarray],
                               guessed: set[int]) -> None:
    """A new database at ``path`` for ``pycolmap.calibrate_view_graph``: every camera of
    ``scene`` (``has_prior_focal_length`` False for the ids in ``guessed``, which it may
    change; True for the others, which it holds), a trivial rig and frame per view, and per
    pair of ``fundamentals`` an UNCALIBRATED two-view geometry with that F (pixels, COLMAP
    convention) and the pair's matches as inliers. No keypoints: calibrate_view_graph reads
    them only to re-estimate poses, which rotonly does itself."""
    pycolmap = import_pycolmap()
    view_offset = id_offset(scene.views)
    camera_offset = id_offset(scene.intrinsics)
    database = pycolmap.Database.open(str(path))
    try:
        for intrinsic_id in sorted(scene.intrinsics):
            camera = pycolmap_camera(to_colmap_intrinsics(scene.intrinsics[intrinsic_id]), intrinsic_id + camera_offset)
            camera.has_prior_focal_length = intrinsic_id not in guessed
            database.write_camera(camera, use_camera_id=True)
            rig = pycolmap.Rig(rig_id=intrinsic_id + camera_offset)
            rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, intrinsic_id + camera_offset))
            database.write_rig(rig, use_rig_id=True)
        for view_id in sorted(scene.views):
            camera_id = scene.views[view_id].intrinsics_id + camera_offset
            image_id = view_id + view_offset
            database.write_image(pycolmap.Image(name=scene.views[view_id].name, camera_id=camera_id,
                                                image_id=image_id), use_image_id=True)
            frame = pycolmap.Frame(frame_id=image_id, rig_id=camera_id)
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id), image_id))
            database.write_frame(frame, use_frame_id=True)
        for (i, j), F in sorted(fundamentals.items()):
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            geometry.F = np.asarray(F, dtype=np.float64)
            geometry.inlier_matches = np.ascontiguousarray(scene.pairs[(i, j)].matches, dtype=np.uint32).reshape(-1, 2)
            database.write_two_view_geometry(i + view_offset, j + view_offset, geometry)
    finally:
        database.close()


def read_camera_params(path: PathLike, scene: SfMScene) -> dict[int, np.ndarray]:
    """Camera parameters (COLMAP model order) of a database written by
    :func:`write_fundamental_database` for ``scene``, keyed by ``scene``'s intrinsic ids."""
    pycolmap = import_pycolmap()
    camera_offset = id_offset(scene.intrinsics)
    database = pycolmap.Database.open(str(path))
    try:
        return {int(camera.camera_id) - camera_offset: np.array(camera.params, dtype=np.float64)
                for camera in database.read_all_cameras()}
    finally:
        database.close()
