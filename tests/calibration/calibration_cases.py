"""What the calibration tests share (tests/calibration/): the run options they use, the rotation
error of a workspace against ground truth, the Herz-Jesus fixture as COLMAP writes an EXIF camera,
and the comparison of auto with fixed."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from rotonly_cli.evaluation.quality import evaluate
from rotonly_cli.io.detect import read_scene
from rotonly_cli.options import IntrinsicsOptions, RunOptions
from rotonly_cli.pipeline import run_pipeline
from rotonly_cli.scene.types import Intrinsics
from rotonly_cli.simulation.user_cameras import camera_per_view

from helpers import DATA_FIXTURES

#: a camera of the size of Strecha's half-resolution images
CAMERA = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0, 768.0, 512.0, 0.0]))


def run_options(mode: str = "auto") -> RunOptions:
    """One job (the tests' numbers do not depend on scheduling), ``--intrinsics mode``."""
    return RunOptions(jobs=1, intrinsics=IntrinsicsOptions(mode=mode))


def rotation_error(out, gt_path) -> float:
    """Mean rotation error (deg) of the workspace ``out`` against the ground truth ``gt_path``."""
    return evaluate(read_scene(gt_path), read_scene(out / "sfm_data.json")).rotation_error_deg.mean


def herzjesu_exif_database(path, per_image: bool = False):
    """The Herz-Jesu fixture's database written to ``path`` as COLMAP writes a camera whose
    focal the EXIF gives: SIMPLE_RADIAL, that focal (here the right one, marked known), the
    principal point at the image centre, k1 = 0; ``per_image``: COLMAP's default, a copy
    per image. Returns (the given camera, the scene written)."""
    from rotonly_cli.io.colmap import read_database, write_database

    scene = read_database(DATA_FIXTURES / "herzjesu_p8" / "database.db")
    (given,) = scene.intrinsics.values()
    exif = Intrinsics(given.id, "SIMPLE_RADIAL", given.width, given.height,
                      np.array([given.focal_px, given.width / 2, given.height / 2, 0.0]), prior_focal=True)
    scene = replace(scene, intrinsics={given.id: exif})
    scene = camera_per_view(scene) if per_image else scene
    write_database(path, scene)
    return given, scene

def auto_writes_what_fixed_writes(input_path, tmp_path) -> tuple[dict, list[str]]:
    """Runs ``input_path`` with --intrinsics fixed and auto and asserts that the two
    sfm_data.json are the same bytes; returns auto's reports/intrinsics.json and the warnings
    of both runs."""
    outputs, warnings = {}, []
    for mode in ("fixed", "auto"):
        warnings += run_pipeline(input_path, tmp_path / mode, run_options(mode))["warnings"]
        outputs[mode] = (tmp_path / mode / "sfm_data.json").read_bytes()
    assert outputs["auto"] == outputs["fixed"]
    return json.loads((tmp_path / "auto" / "reports" / "intrinsics.json").read_text()), warnings

def largest_shift_px(check: dict) -> float:
    """The largest image shift (px) of any camera and parameter group an adjustment report holds."""
    return max(shift for shifts in check["shifts_px"].values() for shift in shifts.values())
