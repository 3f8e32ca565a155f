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
from rotonly_cli.calibration.adjustment import _parameter_std
from rotonly_cli.errors import InputError
from rotonly_cli.evaluation.quality import evaluate
from rotonly_cli.io.detect import read_scene
from rotonly_cli.options import Intrinsics as Mode
from rotonly_cli.options import IntrinsicsOptions, LoadOptions, RunOptions
from rotonly_cli.pipeline import STAGES, resume, run_pipeline
from rotonly_cli.scene.types import Intrinsics, SfMScene, View
from rotonly_cli.simulation.user_cameras import camera_per_view, simulate_user_cameras, write_inputs

from helpers import DATA_FIXTURES

CAMERA = Intrinsics(1, "SIMPLE_RADIAL", 1536, 1024, np.array([1380.0, 768.0, 512.0, 0.0]))


def _options(mode: str = "auto") -> RunOptions:
    return RunOptions(jobs=1, intrinsics=IntrinsicsOptions(mode=mode))


def _rotation_error(out, gt_path) -> float:
    return evaluate(read_scene(gt_path), read_scene(out / "sfm_data.json")).rotation_error_deg.mean


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


def _zoomed(problem, views: tuple[int, ...], zoom: float):
    """``problem`` with the images ``views`` taken at ``zoom`` x the focal (no distortion):
    their keypoints scaled about the principal point, the one camera of the input unchanged."""
    centre = problem.true.params[1:3]
    keypoints = {v: centre + zoom * (k - centre) if v in views else k for v, k in problem.keypoints.items()}
    return replace(problem, keypoints=keypoints)


@pytest.mark.parametrize("zoom", [1.0, 1.06])
def test_per_image_focals_name_the_images_of_another_zoom(zoom):
    """A zoom lens under one camera (COLMAP's single_camera): three of eight images taken at
    6 % more focal. With a camera each, those three come out at the zoomed focal and the five
    at the true one, within 1 %; without the zoom, no group is found."""
    from rotonly_cli.simulation.user_cameras import user_scene, verified_pairs

    problem = _zoomed(simulate_user_cameras(5, -0.25, 0.0, num_views=8, num_points=2000), (2, 5, 7), zoom)
    scene = user_scene(problem, problem.guessed, verified_pairs(problem))
    calibrated, _ = vg_focals.view_graph_focals(scene, {1}, IntrinsicsOptions())
    scene = cal_rounds.with_intrinsics(scene, calibrated)
    fundamentals = vg_focals.refit_fundamentals(scene, IntrinsicsOptions())
    per_image = vg_focals.per_image_focals(scene, [[1]], fundamentals, IntrinsicsOptions())
    assert per_image["success"] and sorted(per_image["focal_px"]["1"]) == [str(v) for v in range(1, 9)]
    if zoom == 1.0:
        assert per_image["disagree"] == []
        assert calibrated[1].focal_px == pytest.approx(1380.0, rel=0.005)
        return
    (finding,) = per_image["disagree"]
    assert finding["camera"] == 1
    low, high = finding["groups"]
    assert low["views"] == [1, 3, 4, 6, 8] and high["views"] == [2, 5, 7]
    assert low["focal_px"] == pytest.approx(1380.0, rel=0.01)
    assert high["focal_px"] == pytest.approx(1380.0 * zoom, rel=0.01)
    warning = vg_focals.zoom_warning(finding)
    assert "3 (sim_0002.jpg, sim_0005.jpg, sim_0007.jpg)" in warning and "single_camera 0" in warning
    assert "were given camera 9" in vg_focals.zoom_warning(finding, 9)
    # images with fewer fundamental matrices than zoom_min_pairs are not judged; too few left: no check
    assert vg_focals.per_image_focals(scene, [[1]], fundamentals, IntrinsicsOptions(zoom_min_pairs=100)) == {}


@pytest.fixture(scope="module")
def zoomed_inputs(tmp_path_factory):
    """Eight views, three of them (2, 5, 7) taken at 6 % more focal, under one camera: as
    COLMAP's guess (single_camera, focal 25 % off) and as a known camera with the other
    images' true focal (OpenMVG's -k)."""
    problem = _zoomed(simulate_user_cameras(5, -0.25, 0.0, num_views=8, num_points=2000), (2, 5, 7), 1.06)
    root = tmp_path_factory.mktemp("zoomed")
    return problem, write_inputs(root / "guessed", problem), write_inputs(root / "known", problem, true_intrinsics=True)


@pytest.mark.parametrize("which, fmt", [("guessed", "colmap"), ("known", "openmvg")])
def test_images_of_another_zoom_get_a_camera_of_their_own(zoomed_inputs, tmp_path, which, fmt):
    """The zoom check splits the camera: the three zoomed images end on a camera of their
    own at the zoomed focal, the others on theirs, within 0.5 % each; the rotations are
    those of a calibrated capture, where one focal for all (the check off) is far off; the
    warning says what was done; the workspace's stage commands keep the split."""
    _, guessed, known = zoomed_inputs
    paths = {"guessed": guessed, "known": known}[which]
    summary = run_pipeline(paths[fmt], tmp_path / "out", _options())
    scene = read_scene(tmp_path / "out" / "sfm_data.json")
    camera_of = {int(view.name[4:8]): view.intrinsics_id for view in scene.views.values()}
    assert len(set(camera_of.values())) == 2
    assert {camera_of[v] for v in (2, 5, 7)} != {camera_of[v] for v in (1, 3, 4, 6, 8)}
    assert len({camera_of[v] for v in (2, 5, 7)}) == len({camera_of[v] for v in (1, 3, 4, 6, 8)}) == 1
    focal = {v: scene.intrinsics[camera_of[v]].focal_px for v in camera_of}
    assert focal[2] == pytest.approx(1380.0 * 1.06, rel=0.005) and focal[1] == pytest.approx(1380.0, rel=0.005)
    split = _rotation_error(tmp_path / "out", paths["gt"])
    assert any("were given camera" in w for w in summary["warnings"])
    one_focal = run_pipeline(paths[fmt], tmp_path / "one", RunOptions(jobs=1, intrinsics=IntrinsicsOptions(
        zoom_check=False)))
    assert not any("disagree on the focal" in w for w in one_focal["warnings"])
    assert split <= 0.03 and _rotation_error(tmp_path / "one", paths["gt"]) >= 5 * split
    resume(tmp_path / "out", "triangulate")
    assert len(read_scene(tmp_path / "out" / "sfm_data.json").intrinsics) == 2


def test_twins_at_another_zoom_are_warned_about_not_split(zoomed_inputs, tmp_path):
    """COLMAP's camera per image with one guess for all (twins, calibrated as one device):
    the zoomed images are named, and the warning tells what to give them; the cameras stay
    as the input has them (one per image)."""
    problem, _, _ = zoomed_inputs
    paths = write_inputs(tmp_path / "input", problem, formats=("colmap",), camera_per_view=True)
    summary = run_pipeline(paths["colmap"], tmp_path / "out", _options())
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    (finding,) = report["zoom_check"]["disagree"]
    assert [group["views"] for group in finding["groups"]] == [[1, 3, 4, 6, 8], [2, 5, 7]]
    assert report["split_cameras"] == {} and len(summary["intrinsics"]) == 8
    (warning,) = [w for w in summary["warnings"] if "disagree on the focal" in w]
    assert "calibrated as one device: give the images of each zoom their own intrinsics" in warning


def test_strong_distortion_is_no_zoom(tmp_path):
    """A guessed focal 40 % long and k1 = -0.3 (the intrinsics benchmark's seed 1): checked on
    the first view-graph calibration, before the rounds had the distortion, its images fell
    into two groups at 2149 and 3112 px; on the settled distortion they agree, and the one
    camera stays one, at the true focal."""
    problem = simulate_user_cameras(1, 0.4, -0.3, num_views=8, num_points=4000)
    paths = write_inputs(tmp_path / "input", problem, formats=("colmap",))
    summary = run_pipeline(paths["colmap"], tmp_path / "out", _options())
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    assert report["zoom_check"]["disagree"] == [] and report["split_cameras"] == {}
    assert list(summary["intrinsics"]) == ["1"]
    assert summary["intrinsics"]["1"]["end"][0] == pytest.approx(1380.0, rel=0.005)
    assert not any("disagree on the focal" in w for w in summary["warnings"])


@pytest.mark.parametrize("relative, groups", [
    # a zoom: two tight groups 5 % apart (fountain-P11, four of eleven images zoomed)
    ([0.3, 5.2, 0.1, -0.1, 4.8, -0.2, -0.1, 5.0, 0.3, 0.1, 5.2], [[0, 2, 3, 5, 6, 8, 9], [1, 4, 7, 10]]),
    # three of Herz-Jesus-P8's eight images zoomed 3 %
    ([-0.3, 3.2, -0.4, -0.1, 3.1, 0.4, -0.3, 3.5], [[0, 2, 3, 5, 6], [1, 4, 7]]),
    # calibrated cameras' scatter: no gap (Herz-Jesus-P8, fountain-P11)
    ([-0.3, 0.2, -0.4, -0.1, 0.1, 0.3, -0.3, 0.5], None),
    # few fundamental matrices: wild, but no group is tight (entry-P10, castle-P19)
    ([-57.8, -64.6, -0.0, 0.0, -11.3, 0.0, 0.0, -23.2, 0.2, 0.2], None),
    ([0.3, 2.1, 1.0, 0.9, -4.2, -3.6, 0.4, 3.3, -0.6, 0.1, 0.1, -0.2, 0.1, -8.2, -6.8, -2.2, -0.4, 1.0, -0.6], None),
    # one image off is no group (two a side needed), nor a gap under 2 %
    ([0.0, 0.1, -0.1, 0.05, 9.0], None),
    ([0.0, 0.05, 1.5, 1.55], None),
    ([0.0, 0.05, 2.5, 2.55], [[0, 1], [2, 3]]),
    ([0.0, 1.0, 3.5, 4.5], None),  # a gap under three times a group's own range
    ([0.0, 1.0, 9.0], None),  # fewer than four images
])
def test_focal_groups_are_a_zoom_not_the_calibration_scatter(relative, groups):
    """The measured per-image view-graph focals (per cent from the shared one) of docs/tuning.md."""
    focals = {v: 1380.0 * (1 + r / 100) for v, r in enumerate(relative)}
    assert vg_focals.focal_groups(focals, IntrinsicsOptions()) == groups


def test_options_reject_a_zoom_check_that_cannot_split():
    with pytest.raises(InputError, match="zoom_min_images"):
        IntrinsicsOptions(zoom_min_images=3).validate()
    with pytest.raises(InputError, match="zoom_min_gap"):
        IntrinsicsOptions(zoom_min_gap=0.0).validate()


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
    given, scene = _herzjesu_exif_database(tmp_path / "exif.db", per_image=True)
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
    report, _ = _auto_writes_what_fixed_writes(true[fmt], tmp_path)
    assert report["suspect_check"]["calibrated"] == [] and not report["rounds"] and not report["view_graph_calibration"]
    assert _largest_shift_px(report["suspect_check"]) < 1.0


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
    report, warnings = _auto_writes_what_fixed_writes(tmp_path / "in" / input_name, tmp_path)
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


def test_an_exif_focal_two_percent_off_is_calibrated(tmp_path):
    """The Herz-Jesu fixture's database with both focal lengths 2 % short, still marked known
    (an EXIF focal that is off). Its first reconstruction reprojects at 0.32 px, 1.7 noise
    sigmas: under the former thresholds (2.5 sigmas, 0.5 px) nothing was calibrated and the
    rotations ended at 0.241 deg, without a warning. Now the camera is a suspect, calibrated
    to 0.1 % and the rotations are the given-intrinsics run's (0.0193 deg)."""
    from rotonly_cli.io.cameras import parameter_groups
    from rotonly_cli.io.colmap import read_database, write_database

    scene = read_database(DATA_FIXTURES / "herzjesu_p8" / "database.db")
    (camera_id, given), = scene.intrinsics.items()
    params = np.array(given.params, dtype=np.float64)
    params[parameter_groups(given)["focal"]] *= 0.98
    write_database(tmp_path / "exif.db", replace(scene, intrinsics={camera_id: replace(given, params=params)}))
    summary = run_pipeline(tmp_path / "exif.db", tmp_path / "out", _options())
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    camera = report["cameras"][str(camera_id)]
    assert camera["calibrated"] == "suspect" and camera["prior_focal"] is True
    assert camera["end"]["params"][:2] == pytest.approx(np.asarray(given.params)[:2], rel=0.002)
    assert summary["num_registered"] == 8
    assert _rotation_error(tmp_path / "out", DATA_FIXTURES / "herzjesu_p8" / "gt_dense_cameras") < 0.025


def _herzjesu_exif_database(path, per_image: bool = False):
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


def _auto_writes_what_fixed_writes(input_path, tmp_path) -> tuple[dict, list[str]]:
    """Runs ``input_path`` with --intrinsics fixed and auto and asserts that the two
    sfm_data.json are the same bytes; returns auto's reports/intrinsics.json and the warnings
    of both runs."""
    outputs, warnings = {}, []
    for mode in ("fixed", "auto"):
        warnings += run_pipeline(input_path, tmp_path / mode, _options(mode))["warnings"]
        outputs[mode] = (tmp_path / mode / "sfm_data.json").read_bytes()
    assert outputs["auto"] == outputs["fixed"]
    return json.loads((tmp_path / "auto" / "reports" / "intrinsics.json").read_text()), warnings


def _largest_shift_px(check: dict) -> float:
    """The largest image shift (px) of any camera and parameter group an adjustment report holds."""
    return max(shift for shifts in check["shifts_px"].values() for shift in shifts.values())


def test_a_default_principal_point_is_checked_and_calibrated(tmp_path):
    """The Herz-Jesu fixture's database as COLMAP writes it for a camera whose focal the
    EXIF gives: SIMPLE_RADIAL, that focal (here the right one), the principal point at the
    image centre, k1 = 0, the focal marked known. The true principal point is 11 px off the
    centre; the first reconstruction reprojects as well as a calibrated camera's, so no
    suspect test sees it, and with it as given the rotations end at 0.088 deg (0.019 deg with
    the true camera). One adjustment on that reconstruction moves it by 11 px: the camera is
    calibrated, the principal point ends within 1 px of the truth and the rotations at
    0.027 deg."""
    given, _ = _herzjesu_exif_database(tmp_path / "exif.db")
    camera_id = given.id
    summary = run_pipeline(tmp_path / "exif.db", tmp_path / "out", _options())
    report = json.loads((tmp_path / "out" / "reports" / "intrinsics.json").read_text())
    camera = report["cameras"][str(camera_id)]
    assert camera["calibrated"] == "centred principal point"
    assert report["centred_principal_point_check"]["shifts_px"][str(camera_id)]["principal_point"] > 9.0
    assert np.hypot(*(np.asarray(camera["end"]["params"][1:3]) - np.asarray(given.params)[2:4])) < 1.5
    assert summary["num_registered"] == 8
    assert _rotation_error(tmp_path / "out", DATA_FIXTURES / "herzjesu_p8" / "gt_dense_cameras") < 0.035


@pytest.mark.parametrize("fmt", ["colmap", "openmvg"])
def test_a_centred_principal_point_that_is_right_is_kept(tmp_path, fmt):
    """A simulated camera whose principal point is at the image centre, given right: the
    check's adjustment moves it by < 1 px, nothing is calibrated, and the run writes what
    --intrinsics fixed writes."""
    problem = simulate_user_cameras(3, 0.0, 0.0, num_views=6, num_points=2000, noise_px=0.3)
    inputs = write_inputs(tmp_path / "true", problem, true_intrinsics=True)
    report, _ = _auto_writes_what_fixed_writes(inputs[fmt], tmp_path)
    check = report["centred_principal_point_check"]
    assert len(check["cameras"]) == 1 and check["calibrated"] == [] and not report["rounds"]
    assert _largest_shift_px(check) < 1.0


# ============================================================================ real repeated structure

CASTLE = DATA_FIXTURES / "castle_p19_openmvg"
#: castle-P19's ground-truth camera (Strecha's files, COLMAP's pixel convention): f, cx, cy
CASTLE_TRUE = np.array([1380.91, 760.595, 503.655])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_wrong_focal_is_calibrated_despite_repeated_structure(tmp_path, seed):
    """castle-P19's OpenMVG matches (repeated windows and arches), the given focal 20 % too
    long and the principal point at the image centre. Wrong matches that survive the rejection
    pull a squared-loss adjustment: its principal point went 765 -> 773 px over the rounds
    (truth 760.6), the focal to -0.35 %, and the rotations to 0.259 deg. Under the Huber loss
    (``ba_huber_px``) the rounds end 2.8 px and -0.11 % from the truth, at 0.0945 deg: within
    castle-P19's seed spread with the true intrinsics (0.065-0.113 deg), below OpenMVG's own
    0.116 deg. Seed 1: 0.0983 deg; when the significance test took the residuals' sigma from
    the errors before the adjustment (5-9 x those after it), its second round's principal
    point (765.6, 505.4) was 1.9 sigmas from the centre, not taken, and the run ended at
    0.333 deg."""
    sfm_data = json.loads((CASTLE / "openmvg" / "sfm_data.json").read_text())
    camera = sfm_data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]
    camera["focal_length"] *= 1.2
    camera["principal_point"] = [camera["width"] / 2, camera["height"] / 2]
    (tmp_path / "sfm_data.json").write_text(json.dumps(sfm_data))
    options = replace(_options(), matches_dir=str(CASTLE / "openmvg"), load=LoadOptions(seed=seed))
    summary = run_pipeline(tmp_path / "sfm_data.json", tmp_path / "out", options)
    assert summary["num_registered"] == 19
    end = np.asarray(summary["intrinsics"]["0"]["end"])
    assert abs(end[0] / CASTLE_TRUE[0] - 1.0) < 0.002
    assert np.hypot(*(end[1:3] - CASTLE_TRUE[1:3])) < 5.0
    assert _rotation_error(tmp_path / "out", CASTLE / "gt_dense_cameras") < 0.116


def test_a_right_camera_is_kept_when_the_matches_are_noisy(tmp_path):
    """castle-P19 matched sequentially (the bundled fixture) with 0.7 px of detector noise added
    to every keypoint, its camera given and right. The matches fit essential matrices at
    0.75 px, so a quick estimation pass checks the camera; one adjustment on that rough
    reconstruction put fy 1.4 % long (7.4 px of image shift), and with the fixed 4.6 px limit
    the run calibrated it: fy 1401.8 px, 0.462 deg over the 19 views (15 s). At that noise the
    limit is 13.9 px: the camera stays as given (0.352 deg)."""
    from rotonly_cli.io.colmap import read_database, write_database

    sequential = DATA_FIXTURES / "castle_p19_sequential"
    scene = read_database(sequential / "database.db")
    rng = np.random.default_rng(0)
    noisy = {v: keypoints + rng.normal(scale=0.7, size=keypoints.shape) for v, keypoints in scene.keypoints.items()}
    write_database(tmp_path / "noisy.db", replace(scene, keypoints=noisy))
    summary = run_pipeline(tmp_path / "noisy.db", tmp_path / "out", _options())
    (camera,) = summary["intrinsics"].values()
    assert camera["end"] == camera["start"]
    log = (tmp_path / "out" / "run.log").read_text()
    assert "quick estimation pass checks the cameras" in log and "calibrating" not in log
    assert _rotation_error(tmp_path / "out", sequential / "ground_truth") < 0.4


def test_parameter_std_from_the_adjustment_covariance_and_its_image_cap():
    """The standard deviations come from pycolmap's covariance of the adjustment (one per camera
    parameter, positive) times the residuals' sigma after it: 0.5 px of keypoint noise is
    measured as 0.5 px (within 8 %), where the points' stored errors still hold those of the
    start, whose focal was 2 % long, and a point sent far off does not move it. Beyond
    ``covariance_max_images`` (its cost grows as the cube of the images: 85 s at 1000) none
    is computed and the image-shift limit alone decides."""
    import pycolmap

    synthetic = pycolmap.SyntheticDatasetOptions()
    synthetic.num_rigs, synthetic.num_cameras_per_rig, synthetic.num_frames_per_rig = 1, 1, 6
    synthetic.num_points3D = 300
    reconstruction = pycolmap.synthesize_dataset(synthetic)
    rng = np.random.default_rng(0)
    for image_id in reconstruction.reg_image_ids():
        for point in reconstruction.images[image_id].points2D:
            point.xy = point.xy + rng.normal(scale=0.5, size=2)
    [camera] = reconstruction.cameras.values()
    camera.params = camera.params * np.where(np.arange(len(camera.params)) == 0, 1.02, 1.0)  # the focal 2 % long
    reconstruction.update_point_3d_errors()
    ba_options = pycolmap.BundleAdjustmentOptions()
    ba_options.refine_focal_length = ba_options.refine_principal_point = ba_options.refine_extra_params = True
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba_options, config, reconstruction)
    adjuster.solve()
    [camera_id] = list(reconstruction.cameras)
    std = _parameter_std(reconstruction, adjuster, [camera_id], 0, IntrinsicsOptions())
    assert std[camera_id].shape == (len(reconstruction.cameras[camera_id].params),)
    assert np.all(std[camera_id] > 0) and np.all(np.isfinite(std[camera_id]))
    sigma = adjustment.residual_sigma_px(reconstruction)
    assert abs(sigma / 0.5 - 1) < 0.08
    assert reconstruction.compute_mean_reprojection_error() > 4 * sigma  # the stored errors: before
    far = next(iter(reconstruction.points3D.values()))
    far.xyz = far.xyz * 1e6
    assert adjustment.residual_sigma_px(reconstruction) == pytest.approx(sigma, rel=0.02)
    capped = IntrinsicsOptions(covariance_max_images=5)
    assert _parameter_std(reconstruction, adjuster, [camera_id], 0, capped) == {}


def test_bad_intrinsics_options_of_the_flat_ground_checks():
    for bad in (dict(min_fundamental_pairs=0), dict(covariance_max_images=-1), dict(rotation_fit_max_matches=7),
                dict(min_change_sigmas=-0.5)):
        with pytest.raises(InputError):
            IntrinsicsOptions(**bad).validate()


# ============================================================================ views without a camera

HERZ = DATA_FIXTURES / "herzjesu_p8"
HERZ_FOCAL = 0.5 * (1379.74 + 1382.08)  # the GT camera's fx, fy


def test_views_without_a_camera_share_a_guess_per_image_size():
    """OpenMVG's listing leaves the intrinsic of an image without EXIF focal undefined: the
    views of one size share one camera with COLMAP's guess, marked as one, normalized with it,
    and the principal point of the given cameras of that size if there are any (else the
    centre); views with a camera keep theirs; ``fixed`` guesses none; a view without its size
    cannot be guessed."""
    from rotonly_cli.io.openmvg import UNDEFINED_INDEX

    given = replace(CAMERA, id=3, params=np.array([1380.0, 760.0, 505.0, 0.0]), prior_focal=True)
    scene = SfMScene(intrinsics={3: given})
    sizes = {0: (1536, 1024), 1: (1536, 1024), 2: (800, 600), 3: (1536, 1024)}
    for view_id, (width, height) in sizes.items():
        scene.views[view_id] = View(view_id, f"{view_id}.jpg", 3 if view_id == 3 else UNDEFINED_INDEX,
                                    width=width, height=height)
        scene.keypoints[view_id] = np.array([[width / 2, height / 2], [width / 2 + 100.0, height / 2]])
    scene.normalized[3] = np.zeros((2, 2))
    out, guessed = guesses.guess_missing_cameras(scene, Mode.AUTO, openmvg=True)
    assert guessed == [0, 1, 2] and scene.views[0].intrinsics_id == UNDEFINED_INDEX  # the input is untouched
    assert out.views[0].intrinsics_id == out.views[1].intrinsics_id == 4 and out.views[2].intrinsics_id == 5
    assert out.views[3].intrinsics_id == 3 and out.intrinsics[3] is given
    wide, small = out.intrinsics[4], out.intrinsics[5]
    assert wide.model == "pinhole_radial_k1" and wide.prior_focal is False
    np.testing.assert_allclose(wide.params, [1.2 * 1536, 760.0, 505.0, 0.0])
    np.testing.assert_allclose(small.params, [1.2 * 800, 400.0, 300.0, 0.0])
    np.testing.assert_allclose(out.normalized[2], [[0.0, 0.0], [100.0 / 960.0, 0.0]], atol=1e-12)
    assert guesses.cameras_to_calibrate(out, Mode.AUTO) == {4, 5}
    assert guesses.guess_missing_cameras(scene, Mode.FIXED, openmvg=True) == (scene, [])
    colmap = guesses.guess_missing_cameras(scene, Mode.REFINE, openmvg=False)[0]
    assert colmap.intrinsics[4].model == "SIMPLE_RADIAL"
    scene.views[1] = replace(scene.views[1], width=None)
    with pytest.raises(InputError, match="image size"):
        guesses.guess_missing_cameras(scene, Mode.AUTO, openmvg=True)


def _without_intrinsics(tmp_path, views=None):
    """The Herz-Jesu fixture's OpenMVG project with the intrinsic of ``views`` (list
    positions; None: all, and no intrinsic left) undefined, as the image listing writes
    images without EXIF focal."""
    sfm_data = json.loads((HERZ / "openmvg" / "sfm_data.json").read_text())
    for k, view in enumerate(sfm_data["views"]):
        if views is None or k in views:
            view["value"]["ptr_wrapper"]["data"]["id_intrinsic"] = 4294967295
    if views is None:
        sfm_data["intrinsics"] = []
    (tmp_path / "sfm_data.json").write_text(json.dumps(sfm_data))
    return tmp_path / "sfm_data.json"


def test_an_openmvg_project_without_exif_is_calibrated(tmp_path):
    """Every view's intrinsic undefined (OpenMVG's own global SfM stops there: "Rotation
    Averaging failure"): one guessed camera, calibrated to within 0.3 % of the GT focal, every
    view registered at 0.0275 deg (OpenMVG's project with its focal given: 0.0404 deg), and an
    sfm_data.json that holds the calibrated camera."""
    input_path = _without_intrinsics(tmp_path)
    summary = run_pipeline(input_path, tmp_path / "out", replace(_options(), matches_dir=str(HERZ / "openmvg")))
    assert summary["num_registered"] == 8
    (camera,) = read_scene(tmp_path / "out" / "sfm_data.json").intrinsics.values()
    assert camera.model == "pinhole_radial_k1" and abs(camera.focal_px / HERZ_FOCAL - 1) < 3e-3
    assert _rotation_error(tmp_path / "out", HERZ / "gt_dense_cameras") < 0.035
    load = json.loads((tmp_path / "out" / "reports" / "load.json").read_text())
    assert load["views_given_a_guessed_camera"] == list(range(8))


def test_fixed_cannot_use_views_without_a_camera(tmp_path):
    """--intrinsics fixed guesses no camera: with none left a one-line input error, nothing
    written; with one view's undefined the other seven are reconstructed and the warning names
    the view and why (it crashed in the tracks before); auto registers all eight, as accurate
    as with its camera given (0.0400 deg against 0.0404; with the guess's principal point at
    the centre, 10 px off: 0.105 deg)."""
    options = replace(_options("fixed"), matches_dir=str(HERZ / "openmvg"))
    (tmp_path / "all").mkdir()
    with pytest.raises(InputError, match="8 of 8 views have no camera"):
        run_pipeline(_without_intrinsics(tmp_path / "all"), tmp_path / "all" / "out", options)
    assert not (tmp_path / "all" / "out").exists()
    (tmp_path / "one").mkdir()
    input_path = _without_intrinsics(tmp_path / "one", views=[5])
    summary = run_pipeline(input_path, tmp_path / "one" / "fixed", options)
    assert summary["num_registered"] == 7 and summary["unregistered_views"] == [5]
    assert any("view(s) 5 have no camera in the input" in warning for warning in summary["warnings"])
    summary = run_pipeline(input_path, tmp_path / "one" / "auto", replace(options, intrinsics=IntrinsicsOptions()))
    assert summary["num_registered"] == 8
    assert _rotation_error(tmp_path / "one" / "auto", HERZ / "gt_dense_cameras") < 0.045
