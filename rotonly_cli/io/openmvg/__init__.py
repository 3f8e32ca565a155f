"""OpenMVG 2.x files <-> rotonly dataclasses (formats.md §1-§2, pitfalls §6).

``sfm_data`` reads ``sfm_data.json`` (cereal JSON), ``sfm_data_writer`` writes it,
``features`` and ``matches`` handle ``<stem>.feat``, ``matches.*.txt|bin`` and pairs files,
``cameras`` the OpenMVG camera models (forward model and OpenMVG's own iterative
undistortion), ``project`` whole projects (``read_project`` / ``write_project``).

Pixel convention: OpenMVG puts the centre of the top-left pixel at (0, 0), rotonly (COLMAP) at
(0.5, 0.5). Keypoints, landmark observations ``x`` and the principal point get +0.5 when read
and -0.5 when written, here and nowhere else (architecture.md "Conventions").
"""

from rotonly_cli.io.openmvg.cameras import (
                                            INTRINSIC_DISTORTION_FIELDS,
                                            PIXEL_OFFSET,
                                            add_distortion,
                                            distort_project,
                                            remove_distortion,
                                            undistort_normalize,
)
from rotonly_cli.io.openmvg.features import read_feature_table, read_features, write_features
from rotonly_cli.io.openmvg.matches import matches_bytes, read_matches, read_pairs, write_matches, write_pairs
from rotonly_cli.io.openmvg.project import image_root, project_files, read_project, write_project
from rotonly_cli.io.openmvg.sfm_data import UNDEFINED_INDEX, read_sfm_data
from rotonly_cli.io.openmvg.sfm_data_writer import sfm_data_bytes, sfm_data_document, write_sfm_data

__all__ = [
    "INTRINSIC_DISTORTION_FIELDS", "PIXEL_OFFSET", "UNDEFINED_INDEX", "add_distortion", "distort_project",
    "image_root", "matches_bytes", "project_files", "read_feature_table", "read_features", "read_matches",
    "read_pairs", "read_project", "read_sfm_data", "remove_distortion", "sfm_data_bytes", "sfm_data_document",
    "undistort_normalize", "write_features", "write_matches", "write_pairs", "write_project", "write_sfm_data",
]
