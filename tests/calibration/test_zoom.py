"""The zoom check of the calibration (calibration/focals.py, calibration.Calibration.check_zoom):
images taken at another zoom under one camera get a camera of their own, twins are warned
about, distortion and the calibration's scatter are no zoom (simulated user inputs)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from rotonly_cli.calibration import focals as vg_focals
from rotonly_cli.calibration import rounds as cal_rounds
from rotonly_cli.errors import InputError
from rotonly_cli.io.detect import read_scene
from rotonly_cli.options import IntrinsicsOptions, RunOptions
from rotonly_cli.pipeline import resume, run_pipeline
from rotonly_cli.simulation.user_cameras import simulate_user_cameras, write_inputs

from calibration_cases import rotation_error as _rotation_error
from calibration_cases import run_options as _options


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
