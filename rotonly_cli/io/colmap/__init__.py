"""COLMAP databases and sparse models <-> rotonly dataclasses (formats.md §4).

Everything goes through pycolmap 4.2.1 (``Database``, ``Reconstruction``, ``Camera``): blob
layouts, pair ids and camera models are pycolmap's business, not re-implemented here. One
exception for speed: the sparse-model writer assembles ``points3D.bin`` (and the point links
of ``images.bin``) with numpy (formats.md §4.8) and has pycolmap read them back, compute the
errors and write the final model, instead of one Python object per point and observation.

``cameras`` converts camera models (and a COLMAP-read scene to OpenMVG's conventions),
``database`` reads and writes databases (``database_check`` checks them first), ``model`` sparse
models.

Conventions kept at this boundary (architecture.md "Conventions", formats.md §4.3/§4.5):
- view id = COLMAP image id, intrinsics id = COLMAP camera id (COLMAP ids are > 0, so a scene
  with id 0 — OpenMVG — is shifted by +1 when written, see ``database.id_offset``);
- keypoints stay in COLMAP's pixel convention (as stored), ``normalized`` comes from
  ``Camera.cam_from_img`` (pycolmap's own undistortion);
- a pair (i, j) has i = the smaller image id = COLMAP ``image1``; its inlier matches index
  (i, j) and the stored ``cam2_from_cam1`` is ``R_j_from_i`` / ``t_j_from_i``.

pycolmap's ``Database.open`` rewrites bookkeeping bytes of a database it opens even if only
reads follow (measured: the md5 of a Strecha DB changed), so inputs are read through a
temporary copy and are never touched.
"""

from rotonly_cli.io.colmap.cameras import (
                                           colmap_to_openmvg,
                                           normalize_keypoints,
                                           pycolmap_camera,
                                           to_colmap_intrinsics,
                                           to_openmvg_scene,
)
from rotonly_cli.io.colmap.database import id_offset, read_database, write_database
from rotonly_cli.io.colmap.database_check import REQUIRED_TABLES, check_database
from rotonly_cli.io.colmap.model import read_model, scene_from_reconstruction, to_reconstruction, write_model

__all__ = ["REQUIRED_TABLES", "check_database", "colmap_to_openmvg", "id_offset", "normalize_keypoints",
           "pycolmap_camera", "read_database", "read_model", "scene_from_reconstruction", "to_colmap_intrinsics",
           "to_openmvg_scene", "to_reconstruction", "write_database", "write_model"]
