"""calibration/ and the calibrated chain of chain/calibrate.py (issue 20): guessed focal lengths
and unknown distortion, on simulated user inputs (simulation/user_cameras.py) and the bundled
calibrated fixtures. The small, fast version of scripts/bench/intrinsics.py is here."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from rotonly_cli.calibration import adjustment, guesses, noise
from rotonly_cli.calibration import focals as vg_focals
from rotonly_cli.calibration import rounds as cal_rounds
from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import read_scene
from rotonly_cli.options import Intrinsics as Mode
from rotonly_cli.options import IntrinsicsOptions, RunOptions
from rotonly_cli.pipeline import STAGES, resume, run_pipeline
from rotonly_cli.scene.types import Intrinsics, SfMScene, View
from rotonly_cli.simulation.user_cameras import camera_per_view, simulate_user_cameras, write_inputs

from calibration_cases import CAMERA, auto_writes_what_fixed_writes, herzjesu_exif_database, largest_shift_px
from calibration_cases import rotation_error as _rotation_error
from calibration_cases import run_options as _options
from helpers import DATA_FIXTURES

# ============================================================================ pieces

def test_options_reject_a_loss_scale_that_is_not_positive():
    with pytest.raises(InputError, match="ba_huber_px"):
        IntrinsicsOptions(ba_huber_px=0.0).validate()
    assert IntrinsicsOptions(ba_huber_px=None).validate().ba_huber_px is None  # squared loss


def test_options_reject_a_negative_centre_tolerance():
    with pytest.raises(InputError, match="centred_principal_point_px"):
        IntrinsicsOptions(centred_principal_point_px=-1.0).validate()
    assert IntrinsicsOptions(centred_principal_point_px=None).validate().centred_principal_point_px is None


def test_a_principal_point_at_the_image_centre_reads_as_a_default():
    assert guesses.centred_principal_point(CAMERA, 0.5)  # COLMAP's default: (w/2, h/2)
    # OpenMVG's image listing writes (w/2, h/2) in its convention: +0.5 px in COLMAP's
    openmvg = Intrinsics(0, "pinhole_radial_k3", 1536, 1024, np.array([1380.0, 768.5, 512.5, 0.0, 0.0, 0.0]))
    assert guesses.centred_principal_point(openmvg, 0.5)
    calibrated = Intrinsics(1, "PINHOLE", 1536, 1024, np.array([1379.74, 1382.08, 760.595, 503.655]))
    assert not guesses.centred_principal_point(calibrated, 0.5)
    assert not guesses.centred_principal_point(replace(CAMERA, params=np.array([1380.0, 768.0, 513.0, 0.0])), 0.5)


def test_cameras_to_calibrate_by_mode():
    scene = SfMScene(intrinsics={1: CAMERA, 2: Intrinsics(2, "PINHOLE", 10, 10, np.ones(4), prior_focal=False)})
    assert guesses.cameras_to_calibrate(scene, Mode.FIXED) == set()
    assert guesses.cameras_to_calibrate(scene, Mode.AUTO) == {2}
    assert guesses.cameras_to_calibrate(scene, Mode.REFINE) == {1, 2}


def test_shift_px_measures_how_far_a_change_moves_the_image():
    moved = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0, 771.0, 508.0, 0.0]))
    assert adjustment.shift_px(CAMERA, moved) == pytest.approx(5.0)
    longer = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0 * 1.01, 768.0, 512.0, 0.0]))
    assert adjustment.shift_px(CAMERA, longer) == pytest.approx(0.01 * adjustment.half_diagonal(CAMERA), rel=1e-6)


def test_gate_keeps_only_significant_groups():
    options = IntrinsicsOptions()  # 0.5 % of the half diagonal: 4.6 px here
    estimate = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0 * 1.002, 760.0, 511.0, 1e-4]))
    gated, shifts = adjustment.gate(CAMERA, estimate, options)
    assert gated.params.tolist() == [1380.0, 760.0, 511.0, 0.0]  # only the principal point moved enough
    assert shifts["principal_point"] == pytest.approx(np.hypot(8, 1)) and shifts["focal"] < 4.6
    big = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1500.0, 768.5, 512.0, -0.2]))
    assert adjustment.gate(CAMERA, big, options)[0].params.tolist() == [1500.0, 768.0, 512.0, -0.2]
    # a guessed focal takes the estimate however small the change
    assert adjustment.gate(CAMERA, estimate, options, frozenset({"focal"}))[0].params.tolist() == \
        [1380.0 * 1.002, 760.0, 511.0, 0.0]


def test_a_change_within_its_uncertainty_is_not_significant():
    """Beyond the shift limit, a group changes only if some parameter moved by more than
    ``min_change_sigmas`` of its standard deviation in the adjustment: a focal 16 px off (14 px
    of image shift, limit 4.6 px) is taken at std 2 px, not at std 16 px (flat ground seen
    from above: the focal trades for the flying height)."""
    options = IntrinsicsOptions()
    estimate = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1364.0, 768.0, 512.0, 0.0]))
    assert adjustment.gate(CAMERA, estimate, options)[0].params[0] == 1364.0
    assert adjustment.gate(CAMERA, estimate, options,
                           parameter_std=np.array([2.0, 1.0, 1.0, 1e-3]))[0].params[0] == 1364.0
    assert adjustment.gate(CAMERA, estimate, options,
                           parameter_std=np.array([16.0, 1.0, 1.0, 1e-3]))[0].params[0] == 1380.0
    # a guess is taken whatever its uncertainty
    assert adjustment.gate(CAMERA, estimate, options, frozenset({"focal"}),
                      parameter_std=np.array([16.0, 1.0, 1.0, 1e-3]))[0].params[0] == 1364.0
    assert adjustment.change_sigmas(CAMERA, estimate, np.array([16.0, 1.0, 0.0, 1e-3])) == {
        "focal": 1.0, "principal_point": 0.0, "distortion": 0.0}
    with pytest.raises(InputError):
        IntrinsicsOptions(min_change_sigmas=-1.0).validate()


def test_the_noise_of_a_flat_field_comes_from_its_homographies():
    """A survey of flat ground: every pair is PLANAR_OR_PANORAMIC (or WATERMARK), none holds a
    fundamental matrix, so the noise sigma the suspect threshold needs was not measured and the
    threshold fell to its 0.3 px floor: a right camera reprojecting at 0.71 px (0.5 px of noise)
    was calibrated, 12 s for nothing (3 x 8 views). The homographies give it."""
    from rotonly_cli.simulation.user_cameras import simulate_survey, user_scene, verified_pairs

    problem = simulate_survey(0, num_points=5000)
    pairs = verified_pairs(problem)
    assert {pair.config for pair in pairs.values()} <= {"PLANAR_OR_PANORAMIC", "WATERMARK"}
    scene = user_scene(problem, problem.true, pairs)
    options = IntrinsicsOptions()
    assert noise.homography_noise_sigma_px(scene, options) == pytest.approx(0.5, rel=0.05)
    assert noise.projective_noise_sigma_px(scene, options) == noise.homography_noise_sigma_px(scene, options)
    assert guesses.suspect_threshold_px(noise.projective_noise_sigma_px(scene, options), options) > 0.7


def test_significance_grows_with_the_keypoint_noise():
    """An estimate from noisier matches scatters more: above ``min_shift_noise_px`` the limit
    grows in proportion (0.75 px: 3 x 4.6 px here), below it and unmeasured it is as given."""
    options = IntrinsicsOptions()
    limit = options.min_shift * adjustment.half_diagonal(CAMERA)
    assert adjustment.shift_limit_px(CAMERA, options) == adjustment.shift_limit_px(CAMERA, options, 0.2) == limit
    assert adjustment.shift_limit_px(CAMERA, options, 0.75) == pytest.approx(3 * limit)
    estimate = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0, 776.0, 512.0, 0.0]))  # 8 px
    assert adjustment.gate(CAMERA, estimate, options, noise_sigma_px=0.2)[0].params[1] == 776.0
    assert adjustment.gate(CAMERA, estimate, options, noise_sigma_px=0.75)[0].params[1] == 768.0
    with pytest.raises(InputError):
        IntrinsicsOptions(min_shift_noise_px=0.0).validate()


def test_suspect_threshold_follows_the_noise():
    options = IntrinsicsOptions()
    assert guesses.suspect_threshold_px(None, options) == options.suspect_reprojection_px
    assert guesses.suspect_threshold_px(0.1, options) == options.suspect_reprojection_px
    assert guesses.suspect_threshold_px(1.0, options) == pytest.approx(1.5)
    assert guesses.suspect_cameras({1: 0.2, 2: 4.0}, 1.0) == {2}


def test_warnings_name_the_reprojection_error_and_a_given_focal_that_moved():
    given = {1: CAMERA, 2: Intrinsics(2, "PINHOLE", 10, 10, np.array([100.0, 100.0, 5.0, 5.0]), prior_focal=False)}
    final = {1: Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1450.0, 768.0, 512.0, 0.0])),
             2: Intrinsics(2, "PINHOLE", 10, 10, np.array([150.0, 150.0, 5.0, 5.0]))}
    warnings = cal_rounds.warnings_for(given, final, {1, 2}, 1.5, IntrinsicsOptions())
    assert len(warnings) == 2  # camera 2 was a guess: moving it is the point
    assert "reprojection error 1.50 px" in warnings[0] and "camera 1: focal moved +5.1 %" in warnings[1]
    assert cal_rounds.warnings_for(given, given, set(), 0.3, IntrinsicsOptions()) == []


# ============================================================================ simulated user inputs

@pytest.fixture(scope="module")
def user_inputs(tmp_path_factory):
    """A 6-view capture with f 30 % off in the guess and k1 = -0.2, as both front ends leave
    it, and the same matches with the true intrinsics."""
    problem = simulate_user_cameras(3, 0.3, -0.2, num_views=6, num_points=2000)
    root = tmp_path_factory.mktemp("user_cameras")
    return problem, write_inputs(root / "guessed", problem), write_inputs(root / "true", problem, true_intrinsics=True)


@pytest.fixture(scope="module")
def reference_error(user_inputs, tmp_path_factory):
    """Rotation error of the run with the true intrinsics, per format."""
    _, _, true = user_inputs
    out = tmp_path_factory.mktemp("reference")
    errors = {}
    for fmt in ("colmap", "openmvg"):
        run_pipeline(true[fmt], out / fmt, _options("fixed"))
        errors[fmt] = _rotation_error(out / fmt, true["gt"])
    return errors


def test_view_graph_focal_of_the_simulated_guess(user_inputs):
    problem = simulate_user_cameras(5, -0.25, 0.0, num_views=6, num_points=2000)
    from rotonly_cli.simulation.user_cameras import user_scene, verified_pairs

    scene = user_scene(problem, problem.guessed, verified_pairs(problem))
    calibrated, report = vg_focals.view_graph_focals(scene, {1}, IntrinsicsOptions())
    assert report["success"] and report["num_pairs"] >= 10
    assert calibrated[1].focal_px == pytest.approx(1380.0, rel=0.005)
    assert calibrated[1].params[1:].tolist() == scene.intrinsics[1].params[1:].tolist()  # only the focal


def test_view_graph_focal_of_twin_guesses_is_one():
    """A camera per view with the same guess (COLMAP's default): the twins share the
    view-graph focal, as accurate as the one camera's; a focal each, from about one
    fundamental matrix per camera, ended 65 % off on entry-P10's guessed database."""
    from rotonly_cli.simulation.user_cameras import camera_per_view, user_scene, verified_pairs

    problem = simulate_user_cameras(5, -0.25, 0.0, num_views=6, num_points=2000)
    scene = camera_per_view(user_scene(problem, problem.guessed, verified_pairs(problem)))
    calibrated, report = vg_focals.view_graph_focals(scene, set(scene.intrinsics), IntrinsicsOptions())
    assert report["success"] and sorted(calibrated) == sorted(scene.intrinsics)
    focals = {k.focal_px for k in calibrated.values()}
    assert len(focals) == 1 and focals.pop() == pytest.approx(1380.0, rel=0.005)


@pytest.mark.parametrize("fmt", ["colmap", "openmvg"])
def test_guessed_intrinsics_are_calibrated(user_inputs, reference_error, tmp_path, fmt):
    """COLMAP: prior_focal_length = 0 says the focal is a guess. OpenMVG: a wrong EXIF focal
    and no distortion, found by the reprojection errors. Both end within 0.5 % of the true
    focal, with k1 recovered, and as accurate as the run with the true intrinsics."""
    problem, guessed, _ = user_inputs
    summary = run_pipeline(guessed[fmt], tmp_path / "out", _options())
    assert summary["num_registered"] == summary["num_views"] == 6
    end = next(iter(summary["intrinsics"].values()))["end"]
    assert end[0] == pytest.approx(1380.0, rel=0.005)
    assert end[3] == pytest.approx(-0.2, abs=0.01)
    assert _rotation_error(tmp_path / "out", guessed["gt"]) <= 1.5 * reference_error[fmt]
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    camera = next(iter(report["cameras"].values()))
    assert camera["calibrated"] == ("guess" if fmt == "colmap" else "suspect")
    assert camera["start"]["params"][0] == pytest.approx(1380.0 * 1.3)
    if fmt == "colmap":
        assert summary["warnings"] == []  # a guess is expected to move
    else:  # the given (EXIF) focal was wrong: said so
        assert any("focal moved" in w for w in summary["warnings"])
        assert camera["end"]["model"] == "pinhole_radial_k1"  # OpenMVG's pinhole gained its k1
        # found by the quick estimation pass, before a full chain ran with it: no TRRM or GRRM
        # before the view-graph focal
        log = (tmp_path / "out" / "run.log").read_text()
        calibrated_at = log.index("view-graph calibration")
        assert log.index("quick estimation pass") < calibrated_at < log.index("refine (TRRM)")
        assert log.index("optimize (GRRM)") > calibrated_at


def test_twin_cameras_are_cameras_given_the_same_intrinsics():
    guess = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1843.2, 768.0, 512.0, 0.0]), prior_focal=False)
    given = {1: guess, 2: replace(guess, id=2), 3: replace(guess, id=3, prior_focal=True),
             4: replace(guess, id=4, params=np.array([1843.7, 768.0, 512.0, 0.0])), 5: replace(guess, id=5)}
    assert guesses.twin_cameras(given, {5, 4, 3, 2, 1}) == [[1, 2, 5], [3], [4]]
    assert guesses.twin_cameras(given, {2, 4}) == [[2], [4]]


def test_a_camera_per_image_shares_its_principal_point(tmp_path):
    """COLMAP's feature extractor gives every image its own camera unless told otherwise. A
    principal point shift of one image is, to first order, a rotation of that camera, so
    per-camera estimates scatter (before this: 2.7 px off, the focal 0.22 %, 0.045 deg); the
    cameras given the same guess share one principal point (fountain-P11 with a camera per
    image: 0.188 -> 0.044 deg)."""
    problem = simulate_user_cameras(1, 0.3, 0.0, num_views=6, num_points=2000, principal_offset=(8.0, -6.0))
    paths = write_inputs(tmp_path / "in", problem, ("colmap",), camera_per_view=True)
    summary = run_pipeline(paths["colmap"], tmp_path / "out", _options())
    assert summary["num_registered"] == 6 and len(summary["intrinsics"]) == 6
    ends = np.array([camera["end"] for camera in summary["intrinsics"].values()])
    assert np.abs(ends[:, 1:3] - problem.true.params[1:3]).max() < 1.5
    assert np.abs(ends[:, 0] / 1380.0 - 1.0).max() < 0.001
    assert _rotation_error(tmp_path / "out", paths["gt"]) < 0.02
    rounds = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())["rounds"]
    assert rounds[-1]["principal_point_groups"] == [[1, 2, 3, 4, 5, 6]] and rounds[-1]["adjustments"] == 2


def _exif_camera_per_image(tmp_path, noise_px: float):
    """COLMAP's default with an EXIF focal, simulated: a camera per image, each with the focal
    (here the right one) marked known and the principal point at the centre, 10 px off."""
    from rotonly_cli.io.colmap import read_database, write_database

    problem = simulate_user_cameras(1, 0.0, 0.0, num_views=6, num_points=2000, principal_offset=(8.0, -6.0),
                                    noise_px=noise_px)
    paths = write_inputs(tmp_path / "in", problem, ("colmap",), camera_per_view=True)
    scene = read_database(paths["colmap"])
    exif = {c: replace(k, prior_focal=True) for c, k in scene.intrinsics.items()}
    write_database(tmp_path / "exif.db", replace(scene, intrinsics=exif))
    summary = run_pipeline(tmp_path / "exif.db", tmp_path / "out", _options())
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    ends = np.array([camera["end"] for camera in summary["intrinsics"].values()])
    assert np.all(ends == ends[0])  # calibrated as one camera
    assert np.abs(ends[0, 1:3] - problem.true.params[1:3]).max() < 1.5
    assert _rotation_error(tmp_path / "out", paths["gt"]) < 0.02
    return report


def test_a_camera_per_image_with_a_known_focal_is_checked_as_one_camera(tmp_path):
    """The Herz-Jesu fixture's database as COLMAP writes it by default with an EXIF focal: a
    camera per image, SIMPLE_RADIAL, the right focal marked known, the principal point at the
    centre (11 px off). No camera is a suspect; the centred-principal-point check calibrates
    the eight as one camera: the same EXIF focal is the same zoom, so the twins share focal
    and distortion too, in one adjustment (each image's own focal is weakly fixed: castle-P19's
    database so written moved one view's by 1.9 %)."""
    given, scene = herzjesu_exif_database(tmp_path / "exif.db", per_image=True)
    summary = run_pipeline(tmp_path / "exif.db", tmp_path / "out", _options())
    check = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())["centred_principal_point_check"]
    assert check["calibrated"] == sorted(scene.views) and check["adjustments"] == 1
    assert check["principal_point_groups"] == [sorted(scene.views)]
    ends = np.array([camera["end"] for camera in summary["intrinsics"].values()])
    assert np.all(ends == ends[0]) and summary["num_registered"] == 8
    assert np.hypot(*(ends[0, 1:3] - np.asarray(given.params)[2:4])) < 1.5
    assert _rotation_error(tmp_path / "out", DATA_FIXTURES / "herzjesu_p8" / "gt_dense_cameras") < 0.035


def test_openmvg_intrinsics_per_view_are_checked_as_one_camera(tmp_path):
    """The Herz-Jesu fixture's OpenMVG project as the image listing writes it without
    grouping (``-g 0``): an intrinsic per view, each with the same focal and the principal
    point at the centre. They are twins and are calibrated as one camera (OpenMVG marks no
    focal as a guess): castle-P19's project so written ended at 0.170 deg with a focal per
    view (view 3's moved by 3.9 %), at 0.083 deg shared."""
    from rotonly_cli.io.openmvg import read_sfm_data, write_sfm_data

    source = DATA_FIXTURES / "herzjesu_p8" / "openmvg"
    scene = read_sfm_data(source / "sfm_data.json")
    (given,) = scene.intrinsics.values()
    centre = np.array([given.width, given.height]) / 2 + 0.5  # OpenMVG's (w/2, h/2) in COLMAP's convention
    centred = replace(given, params=np.concatenate([np.asarray(given.params)[:1], centre]))
    write_sfm_data(tmp_path / "sfm_data.json", camera_per_view(replace(scene, intrinsics={given.id: centred})),
                   include_structure=False)
    summary = run_pipeline(tmp_path / "sfm_data.json", tmp_path / "out", replace(_options(), matches_dir=str(source)))
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    ends = np.array([camera["end"] for camera in summary["intrinsics"].values()])
    assert len(ends) == 8 and np.all(ends == ends[0]) and summary["num_registered"] == 8
    checks = [report[key] for key in ("suspect_check", "centred_principal_point_check") if report[key]]
    assert checks and all(check["adjustments"] == 1 and len(check["principal_point_groups"]) == 1 for check in checks)
    assert _rotation_error(tmp_path / "out", DATA_FIXTURES / "herzjesu_p8" / "gt_dense_cameras") < 0.045


@pytest.mark.parametrize("fmt", ["colmap", "openmvg"])
def test_a_suspect_one_adjustment_leaves_in_place_is_kept(user_inputs, tmp_path, fmt):
    """The simulated capture with its true intrinsics (k1 = -0.2, 0.5 px noise) reprojects
    above the suspect threshold, as a camera 2 % off does. One adjustment on that
    reconstruction moves the camera by < 1 px: it stays as given with no round, and the run
    writes what --intrinsics fixed writes (before: a view-graph focal, an estimation pass and
    a round to come back to the given intrinsics, and an sfm_data.json that differed)."""
    _, _, true = user_inputs
    report, _ = auto_writes_what_fixed_writes(true[fmt], tmp_path)
    assert report["suspect_check"]["calibrated"] == [] and not report["rounds"] and not report["view_graph_calibration"]
    assert largest_shift_px(report["suspect_check"]) < 1.0


def test_a_suspect_takes_its_twins_along(tmp_path):
    """At 0.5 px noise five of the six cameras reproject above the suspect threshold and one
    (camera 1) just below it. Calibrated alone, the five left camera 1's principal point as
    given and their own estimate was gated back to the given (the rotations 0.09 deg, as with
    the given intrinsics); twins are one device, so all six are suspects: 0.012 deg."""
    report = _exif_camera_per_image(tmp_path, 0.5)
    assert {camera["calibrated"] for camera in report["cameras"].values()} == {"suspect"}
    assert report["centred_principal_point_check"] is None  # nothing left to check


def test_a_principal_point_seen_in_one_image_is_kept(tmp_path):
    """Cameras given different intrinsics, one image each: their principal points are not
    estimated; focal lengths are."""
    problem = simulate_user_cameras(1, 0.0, 0.0, num_views=6, num_points=2000)
    paths = write_inputs(tmp_path / "in", problem, ("colmap",), true_intrinsics=True)
    run_pipeline(paths["colmap"], tmp_path / "out", _options("fixed"))
    posed = read_scene(tmp_path / "out" / "sfm_data.json")
    view_of = {view.name: view_id for view_id, view in posed.views.items()}
    given = {}
    for name, view_id in view_of.items():
        camera_id = int(name[4:8])
        given[camera_id] = Intrinsics(camera_id, "SIMPLE_RADIAL", 1536, 1024,
                                      np.array([1380.0 + camera_id, 768.0, 512.0, 0.0]))
        posed.views[view_id] = replace(posed.views[view_id], intrinsics_id=camera_id)
    posed = cal_rounds.with_intrinsics(replace(posed, intrinsics=given), {})
    estimated, report = adjustment.estimate_intrinsics(posed, set(given), IntrinsicsOptions(),
                                                  guesses.twin_cameras(given, set(given)))
    assert report["principal_point_groups"] == [] and report["principal_point_kept"] == sorted(given)
    assert report["adjustments"] == 1
    for camera_id, estimate in estimated.items():
        assert estimate.params[1:3].tolist() == [768.0, 512.0]
        assert estimate.params[0] != given[camera_id].params[0]


def test_fixed_uses_the_guess_and_warns(user_inputs, tmp_path):
    _, guessed, _ = user_inputs
    summary = run_pipeline(guessed["colmap"], tmp_path / "out", _options("fixed"))
    camera = next(iter(summary["intrinsics"].values()))
    assert camera["start"] == camera["end"]
    assert any("marked as a guess" in w for w in summary["warnings"])
    assert any(w in (tmp_path / "out" / "run.log").read_text() for w in summary["warnings"])


def test_stage_commands_keep_the_calibrated_intrinsics(user_inputs, tmp_path):
    """`rotonly identify` calibrates the guessed focal from the view graph; the stage commands
    that follow on the workspace use it (state.npz), not the database's guess."""
    from rotonly_cli.io.workspace import load_state

    _, guessed, _ = user_inputs
    out = tmp_path / "ws"
    run_pipeline(guessed["colmap"], out, _options(), stages=("load", "identify"))
    calibrated = load_state(out).options["intrinsics"]
    focal = calibrated["cameras"]["1"]["params"][0]
    assert calibrated["mode"] == "auto" and focal != pytest.approx(1380.0 * 1.3)
    for name in STAGES[2:]:
        summary = resume(out, name, RunOptions(jobs=1))
    assert next(iter(read_scene(out / "sfm_data.json").intrinsics.values())).focal_px == focal
    camera = next(iter(summary["intrinsics"].values()))
    assert camera["start"][0] == pytest.approx(1380.0 * 1.3) and camera["end"][0] == focal


# ============================================================================ calibrated inputs

@pytest.mark.parametrize("input_name", ["database.db", "openmvg/sfm_data.json"])
def test_auto_leaves_calibrated_cameras_alone(tmp_path, input_name):
    """Byte-identical to --intrinsics fixed on calibrated input (the check_identical.py
    --against-fixed guard on the Strecha scenes, here on the bundled fixture)."""
    source = DATA_FIXTURES / "herzjesu_p8"
    shutil.copytree(source, tmp_path / "in")
    report, warnings = auto_writes_what_fixed_writes(tmp_path / "in" / input_name, tmp_path)
    assert warnings == []
    assert "quick estimation pass" not in (tmp_path / "auto" / "run.log").read_text()
    assert report["kept_given_intrinsics"] and not report["rounds"]


def test_views_of_one_camera_change_together():
    scene = SfMScene(intrinsics={1: CAMERA})
    for view_id in (1, 2):
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", 1)
        scene.keypoints[view_id] = np.array([[768.0 + 138.0, 512.0]])
        scene.normalized[view_id] = np.array([[0.1, 0.0]])
    copy = cal_rounds.with_intrinsics(scene, {1: Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024,
                                                       np.array([690.0, 768.0, 512.0, 0.0]))})
    np.testing.assert_allclose(copy.normalized[1], [[0.2, 0.0]])
    np.testing.assert_allclose(copy.normalized[2], [[0.2, 0.0]])
    np.testing.assert_allclose(scene.normalized[1], [[0.1, 0.0]])  # the original is untouched


@pytest.mark.parametrize("focal_factor, settled", [(1.018, False), (1.01, True)])
def test_a_round_that_moves_the_focal_by_more_than_one_and_a_half_percent_has_not_settled(focal_factor, settled):
    """A focal 1.8 % longer shifts the image by 1.8 % of its half diagonal, below
    converged_shift (2 %), and still leaves the rounds going: castle-P19 listed with the
    focal 15 % short stopped after a first round 8.7 % short (4.05 deg)."""
    scene = SfMScene(intrinsics={1: CAMERA})
    for view_id in (1, 2):
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", 1)
        scene.keypoints[view_id] = np.array([[900.0, 600.0]])
        scene.normalized[view_id] = np.array([[0.1, 0.05]])
    calibration = cal_rounds.Calibration(IntrinsicsOptions(), {1: CAMERA}, scene, calibrate={1: "guess"})
    estimate = cal_rounds.with_focal(CAMERA, focal_factor * CAMERA.focal_px)
    calibration._gated_estimates = lambda *args: ({1: estimate}, {"time_s": 0.0})
    assert calibration.estimate(scene) is settled
    report = calibration.steps.rounds[-1]
    assert report["moved"] < IntrinsicsOptions().converged_shift
    assert report["focal_change"] == pytest.approx(focal_factor - 1.0)


def test_rounds_that_do_not_settle_take_the_round_converged_on_the_most_points():
    """castle-P19's default-preset E matches with the focal x0.85: rounds 1480.6 -> 1380.7 ->
    1427.5 -> 1568.5 px on 229 / 1547 / 148 / 285 points, only the second converged; the last
    was written (7.2 deg), the second is right (0.149 deg)."""
    scene = SfMScene(intrinsics={1: CAMERA})
    scene.views[1] = View(1, "1.jpg", 1)
    scene.keypoints[1] = np.array([[900.0, 600.0]])
    scene.normalized[1] = np.array([[0.1, 0.05]])
    calibration = cal_rounds.Calibration(IntrinsicsOptions(), {1: CAMERA}, scene, calibrate={1: "suspect"})
    rounds = [(1480.6, 229, "NO_CONVERGENCE"), (1380.7, 1547, "CONVERGENCE"), (1427.5, 3000, "NO_CONVERGENCE"),
              (1568.5, 285, "NO_CONVERGENCE")]
    calibration.steps.rounds = [{"num_points": points, "termination": termination} for _, points, termination in rounds]
    calibration.round_scenes = [cal_rounds.with_intrinsics(scene, {1: cal_rounds.with_focal(CAMERA, focal)})
                                for focal, _, _ in rounds]
    calibration.scene = calibration.round_scenes[-1]
    calibration.take_best_round()
    assert calibration.scene.intrinsics[1].focal_px == pytest.approx(1380.7)
    assert calibration.steps.unsettled["taken_round"] == 2
    assert calibration.finish(calibration.scene)["unsettled"]["taken_round"] == 2
    # none converged: the most points
    calibration.steps.rounds = [dict(report, termination="NO_CONVERGENCE") for report in calibration.steps.rounds]
    calibration.take_best_round()
    assert calibration.scene.intrinsics[1].focal_px == pytest.approx(1427.5)


def test_a_failed_quick_estimation_pass_falls_back_to_the_full_chain(user_inputs, tmp_path, monkeypatch):
    """The quick pass runs on intrinsics that may be far off; if it finds no reconstruction,
    the run goes on as without it (the full chain with the given intrinsics decides)."""
    from rotonly_cli.chain import calibrate
    from rotonly_cli.errors import AlgorithmError

    _, guessed, _ = user_inputs
    rerun, calls = calibrate._rerun, []

    def failing_first(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise AlgorithmError("fewer than two usable images after scene identification")
        return rerun(*args, **kwargs)

    monkeypatch.setattr(calibrate, "_rerun", failing_first)
    summary = run_pipeline(guessed["openmvg"], tmp_path / "out", _options())
    assert summary["num_registered"] == 6 and len(calls) > 1
    log = (tmp_path / "out" / "run.log").read_text()
    assert "quick estimation pass found no reconstruction" in log
    end = next(iter(summary["intrinsics"].values()))["end"]
    assert end[0] == pytest.approx(1380.0, rel=0.005)  # found by the first reconstruction instead
