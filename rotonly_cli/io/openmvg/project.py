"""Whole OpenMVG projects: sfm_data.json with its features and matches, read and written."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.io.inputs import check_regular_file
from rotonly_cli.io.openmvg.cameras import undistort_normalize
from rotonly_cli.io.openmvg.features import read_features, write_features
from rotonly_cli.io.openmvg.matches import read_matches, write_matches
from rotonly_cli.io.openmvg.sfm_data import CEREAL_MSB, read_sfm_data
from rotonly_cli.io.openmvg.sfm_data_writer import write_sfm_data
from rotonly_cli.scene.types import PairMatches, SfMScene, View

PathLike = str | os.PathLike


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
        "polymorphic_id": CEREAL_MSB | 1,
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
        "polymorphic_id": CEREAL_MSB | 2,
        "polymorphic_name": "SIFT_Regions",
        "ptr_wrapper": {"valid": 1, "data": {"value0": [], "value1": []}},
    },
}


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
        if os.path.lexists(matches_dir / name):
            check_regular_file(matches_dir / name)  # a pipe or a dangling link is an error, not "no file"
            return matches_dir / name
    return None


def image_root(root_path: str, sfm_data_path: PathLike) -> Path | None:
    """The image folder of an sfm_data file, found the way OpenMVG's tools find it:
    ``root_path`` as written, a relative one from the current directory (formats.md §1.1);
    when that is no folder, relative to the sfm_data file's folder (a project moved, or used
    from another directory). None for an empty ``root_path``."""
    if not root_path:
        return None
    root = Path(root_path)
    if root.is_absolute() or root.is_dir():
        return root
    beside = Path(sfm_data_path).parent / root
    return beside if beside.is_dir() else root


def _matches_dir(sfm_data_path: PathLike, matches_dir: PathLike | None, matches_file: PathLike | None) -> Path:
    if matches_dir is not None:
        return Path(matches_dir)
    return (Path(matches_file).parent if matches_file is not None and Path(matches_file).is_file()
            else Path(sfm_data_path).parent)


def project_files(scene: SfMScene, sfm_data_path: PathLike, matches_dir: PathLike | None = None,
                  matches_file: PathLike | None = None) -> tuple[list[str], str | None]:
    """The files :func:`read_project` reads for ``scene``: (the sfm_data file, each view's
    ``.feat`` and the matches file when there is one, in that order; the matches file)."""
    folder = _matches_dir(sfm_data_path, matches_dir, matches_file)
    files = [str(sfm_data_path)] + [str(folder / f"{_feature_stem(scene.views[v])}.feat") for v in sorted(scene.views)]
    match_path = _choose_match_file(folder, matches_file) if folder.is_dir() else None
    if match_path is None:
        return files, None
    return files + [str(match_path)], str(match_path)


def read_project(sfm_data_path: PathLike, matches_dir: PathLike | None = None,
                 matches_file: PathLike | None = None) -> SfMScene:
    """sfm_data.json + ``<stem>.feat`` per view (keypoints + normalized) + matches.

    ``matches_dir`` defaults to the folder of ``matches_file`` if given, else of the
    sfm_data file. Without ``matches_file`` the first of matches.e.bin/.txt, matches.f.*,
    matches.putative.* is used (e/f -> verified, config "E"/"F"; putative -> unverified).
    """
    scene = read_sfm_data(sfm_data_path)
    matches_dir = _matches_dir(sfm_data_path, matches_dir, matches_file)
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
