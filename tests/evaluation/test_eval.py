"""rotonly_cli.evaluation (quality + report) and `rotonly eval`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.evaluation import quality
from rotonly_cli.evaluation.report import format_table, write_report
from rotonly_cli.geometry import so3
from rotonly_cli.scene.types import Intrinsics, Pose, SfMScene, View

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES / "evalquality"
SCENES = ["fountain-P11", "Herz-Jesus-P8", "entry-P10"]


# ---------------------------------------------------------------- scene builders (test-private)

def _scene(names: list[str], R_cam_from_world: np.ndarray, centers: np.ndarray, source: str,
           ids: list[int] | None = None) -> SfMScene:
    ids = list(range(len(names))) if ids is None else ids
    scene = SfMScene(source=source)
    scene.intrinsics[0] = Intrinsics(0, "pinhole", 100, 100, np.array([100.0, 50.0, 50.0]))
    for view_id, name, R, c in zip(ids, names, R_cam_from_world, centers):
        scene.views[view_id] = View(view_id, name, 0, view_id)
        scene.poses[view_id] = Pose(np.array(R, dtype=float), np.array(c, dtype=float))
    return scene


def _read_strecha_minimal(scene_dir: Path) -> SfMScene:
    """Raw Strecha .camera files (formats.md §3.2): R_file is camera->world, kept unprojected."""
    names, rotations, centers = [], [], []
    for path in sorted((scene_dir / "gt_dense_cameras").glob("*.camera")):
        values = np.array(path.read_text().split(), dtype=float)
        rotations.append(values[12:21].reshape(3, 3).T)
        centers.append(values[21:24])
        names.append(path.name[: -len(".camera")])
    return _scene(names, np.array(rotations), np.array(centers), "strecha")


def _read_sfm_data_minimal(path: Path) -> SfMScene:
    """The views + extrinsics of an OpenMVG sfm_data.json; poses re-keyed by view id."""
    data = json.loads(path.read_text())
    extrinsics = {e["key"]: e["value"] for e in data["extrinsics"]}
    names, rotations, centers, ids = [], [], [], []
    for entry in data["views"]:
        view = entry["value"]["ptr_wrapper"]["data"]
        if view["id_pose"] in extrinsics:
            names.append(view["filename"])
            rotations.append(extrinsics[view["id_pose"]]["rotation"])
            centers.append(extrinsics[view["id_pose"]]["center"])
            ids.append(view["id_view"])
    return _scene(names, np.array(rotations), np.array(centers), "openmvg", ids)


def _read_sfm_data(path: Path) -> SfMScene:
    """The project's OpenMVG reader when it is there (io/openmvg/), else the minimal parser."""
    try:
        from rotonly_cli.io.openmvg import read_sfm_data
    except ImportError:
        return _read_sfm_data_minimal(path)
    return read_sfm_data(path)


def _read_strecha(scene_dir: Path) -> SfMScene:
    """The project's Strecha reader when it is there (io/strecha.py), else the minimal parser."""
    try:
        from rotonly_cli.io.detect import read_ground_truth
    except ImportError:
        return _read_strecha_minimal(scene_dir)
    return read_ground_truth(scene_dir)


def _random_scene(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return so3.random_rotations(n, rng), rng.normal(scale=3.0, size=(n, 3))


# ---------------------------------------------------------------- synthetic checks

def test_gt_against_itself_is_zero():
    rng = np.random.default_rng(10)
    R, c = _random_scene(6, rng)
    names = [f"{k:04d}.jpg" for k in range(6)]
    report = quality.evaluate(_scene(names, R, c, "simulation"), _scene(names, R, c, "simulation"))
    assert (report.num_gt, report.num_estimated, report.num_matched) == (6, 6, 6)
    for stats in (report.rotation_error_deg, report.relative_rotation_error_deg, report.position_error,
                  report.evalquality.distance_residual):
        assert stats.max == pytest.approx(0.0, abs=1e-9)
    # evalQuality's acos(trace/3) has a ~1e-6 deg floor at zero (acos is flat at 1), as in OpenMVG
    assert report.evalquality.angular_residual_deg.max == pytest.approx(0.0, abs=1e-5)
    assert report.evalquality.similarity.scale == pytest.approx(1.0, rel=1e-12)


def test_known_similarity_and_per_camera_noise_come_back_exactly():
    """Estimate = GT seen through a similarity, each camera rotated by a known noise E_i.

    R_est_i = R_gt_i E_i A (E_i in pairs ±, so the chordal L2 gauge is exactly A), c_est from
    c_gt = s A c_est + t. Geodesic errors = angles of E_i; evalQuality's angle = acos((1+2cosθ)/3).
    """
    rng = np.random.default_rng(11)
    n_half = 5
    R_gt, c_gt = _random_scene(2 * n_half, rng)
    angles = np.radians(np.array([0.05, 0.3, 1.0, 2.5, 7.0]))
    axes = rng.normal(size=(n_half, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    noise = so3.exp(np.concatenate([axes * angles[:, None], -axes * angles[:, None]]))
    s, A, t = 0.37, so3.random_rotations(1, rng)[0], np.array([4.0, -2.0, 9.0])
    R_est = R_gt @ noise @ A
    c_est = (c_gt - t) @ A / s  # rows: Aᵀ (c_gt - t) / s
    names = [f"img_{k}.png" for k in range(2 * n_half)]
    # estimate view ids deliberately differ from GT ids: matching is by name
    estimate = _scene(names[::-1], R_est[::-1], c_est[::-1], "openmvg", ids=list(range(100, 100 + 2 * n_half)))
    report = quality.evaluate(_scene(names, R_gt, c_gt, "simulation"), estimate)

    expected_geodesic = np.degrees(np.concatenate([angles, angles]))
    got = np.array([cam.rotation_error_deg for cam in report.per_camera])
    assert [cam.name for cam in report.per_camera] == names
    np.testing.assert_allclose(got, expected_geodesic, rtol=1e-9)
    np.testing.assert_allclose(report.rotation_alignment, A, atol=1e-12)
    expected_trace3 = np.degrees(np.arccos((1.0 + 2.0 * np.cos(np.concatenate([angles, angles]))) / 3.0))
    np.testing.assert_allclose(report.evalquality.rotation_angular_residuals, expected_trace3, rtol=1e-9)
    np.testing.assert_allclose(report.evalquality.distance_residuals, 0.0, atol=1e-9)
    assert report.position_error.max == pytest.approx(0.0, abs=1e-9)
    assert report.similarity.scale == pytest.approx(s, rel=1e-12)
    # relative error of pair (k, k + n_half): E_k and E_k⁻¹ compose to twice the angle
    assert report.relative_rotation_error_deg.max == pytest.approx(2 * np.degrees(angles[-1]), rel=1e-9)


def test_hand_computed_four_camera_example():
    """Identity similarity; camera k rotated about z by 0, 1, 5, 10 degrees.

    trace/3 angles by hand: acos((1 + 2 cos θ)/3) = 0, 0.8164931, 4.0820509, 8.1615048 deg
    (30-digit mpmath). OpenMVG's median is the element n//2 = 2 of the sorted values:
    4.0820509 (not the average 2.449 of the middle two). The 0-deg camera comes out at
    ~1e-6 deg, not 0: acos near 1 turns a 1e-16 trace rounding into ~1e-8 rad; OpenMVG's
    formula has the same floor.
    """
    R_gt = np.repeat(np.eye(3)[None], 4, axis=0)
    c = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    theta = np.radians([0.0, 1.0, 5.0, 10.0])
    R_est = so3.exp(np.stack([np.zeros(4), np.zeros(4), theta], axis=1))
    names = ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]
    report = quality.evaluate(_scene(names, R_gt, c, "simulation"), _scene(names, R_est, c, "simulation"))
    np.testing.assert_allclose(report.evalquality.rotation_angular_residuals,
                               [0.0, 0.8164931, 4.0820509, 8.1615048], atol=1e-5)
    stats = report.evalquality.angular_residual_deg
    assert stats.median == pytest.approx(4.0820509, abs=1e-6)
    assert stats.mean == pytest.approx((0.8164931 + 4.0820509 + 8.1615048) / 4, abs=1e-5)
    assert stats.min == pytest.approx(0.0, abs=1e-5) and stats.count == 4
    assert stats.max == pytest.approx(8.1615048, abs=1e-6)
    np.testing.assert_allclose(report.evalquality.distance_residuals, 0.0, atol=1e-12)


def test_missing_and_extra_views_are_reported():
    rng = np.random.default_rng(12)
    R, c = _random_scene(5, rng)
    gt = _scene(["0.jpg", "1.jpg", "2.jpg", "3.jpg", "4.jpg"], R, c, "simulation")
    estimate = _scene(["0.jpg", "1.jpg", "2.jpg", "3.jpg", "9.jpg"], R, c, "simulation")
    del estimate.poses[3]  # a view without a pose is not "estimated"
    report = quality.evaluate(gt, estimate)
    assert (report.num_gt, report.num_estimated, report.num_matched) == (5, 4, 3)
    assert report.missing_in_estimate == ["3.jpg", "4.jpg"]
    assert report.not_in_gt == ["9.jpg"]


def test_matching_falls_back_to_base_names():
    rng = np.random.default_rng(13)
    R, c = _random_scene(3, rng)
    gt = _scene(["0.jpg", "1.jpg", "2.jpg"], R, c, "simulation")
    estimate = _scene(["images/0.jpg", "images/1.jpg", "images/2.jpg"], R, c, "colmap-model")
    assert quality.evaluate(gt, estimate).num_matched == 3


def test_no_common_images_is_an_input_error():
    rng = np.random.default_rng(14)
    R, c = _random_scene(3, rng)
    with pytest.raises(InputError, match="no common posed images"):
        quality.evaluate(_scene(["a", "b", "c"], R, c, "simulation"), _scene(["x", "y", "z"], R, c, "simulation"))


def test_rotation_only_estimate_skips_position_metrics():
    """All estimated centres at the origin: rotations are still scored, positions are not."""
    rng = np.random.default_rng(15)
    R, c = _random_scene(4, rng)
    names = ["a", "b", "c", "d"]
    report = quality.evaluate(_scene(names, R, c, "simulation"), _scene(names, R, np.zeros((4, 3)), "simulation"))
    assert report.rotation_error_deg.max == pytest.approx(0.0, abs=1e-9)
    assert report.position_error is None and report.evalquality is None
    assert any("coincide" in note for note in report.notes)


# ---------------------------------------------------------------- against the real evalQuality

@pytest.mark.parametrize("scene", SCENES)
def test_reproduces_openmvg_evalquality_blob(scene):
    """Per-camera residuals of the real openMVG_main_evalQuality (gt_eval_stats_blob.json)."""
    scene_dir = FIXTURES / scene
    blob = json.loads((scene_dir / "openmvg" / "eval" / "gt_eval_stats_blob.json").read_text())
    report = quality.evaluate(_read_strecha(scene_dir),
                              _read_sfm_data(scene_dir / "openmvg" / "global" / "sfm_data.json"))
    assert report.num_gt == blob["gt_num_poses"] and report.num_estimated == blob["eval_num_poses"]
    np.testing.assert_allclose(report.evalquality.rotation_angular_residuals,
                               blob["rotation_angular_residuals"], rtol=0, atol=1e-4)
    np.testing.assert_allclose(report.evalquality.distance_residuals, blob["distance_residuals"], rtol=1e-3)
    # the clamped zeros of the blob (fountain) come out as exact zeros too
    zeros = np.array(blob["rotation_angular_residuals"]) == 0.0
    assert np.all(np.array(report.evalquality.rotation_angular_residuals)[zeros] == 0.0)


def _console_stats(path: Path) -> dict[str, dict[str, float]]:
    """The "Baseline/Angular error statistics" block evalQuality printed (6 significant digits)."""
    stats: dict[str, dict[str, float]] = {}
    block = None
    for line in path.read_text().splitlines():
        if "error statistics" in line:
            block = "distance" if line.startswith("Baseline") else "angle"
            stats[block] = {}
        elif ":" in line and block:
            key, value = line.strip().split(":")
            stats[block][key] = float(value)
    return stats


@pytest.mark.parametrize("gt_scene, estimate, eval_dir", [
    ("Herz-Jesus-P8", "Herz-Jesus-P8/openmvg/global/sfm_data.json", "Herz-Jesus-P8/openmvg/eval"),
    # one camera missing, rotations off by degrees: README.md of that fixture
    ("Herz-Jesus-P8", "Herz-Jesus-P8-perturbed/sfm_data.json", "Herz-Jesus-P8-perturbed"),
])
def test_reproduces_openmvg_console_statistics(gt_scene, estimate, eval_dir):
    """min/mean/median/max as the real tool printed them; n = 8 checks the upper median."""
    report = quality.evaluate(_read_strecha(FIXTURES / gt_scene), _read_sfm_data(FIXTURES / estimate))
    blob = json.loads((FIXTURES / eval_dir / "gt_eval_stats_blob.json").read_text())
    np.testing.assert_allclose(report.evalquality.rotation_angular_residuals,
                               blob["rotation_angular_residuals"], rtol=0, atol=1e-4)
    np.testing.assert_allclose(report.evalquality.distance_residuals, blob["distance_residuals"], rtol=1e-3)
    printed = _console_stats(FIXTURES / eval_dir / "evalquality_console_stats.txt")
    for block, stats in (("distance", report.evalquality.distance_residual),
                         ("angle", report.evalquality.angular_residual_deg)):
        for key in ("min", "mean", "median", "max"):
            assert getattr(stats, key) == pytest.approx(printed[block][key], rel=6e-6), (block, key)
    assert report.num_matched == len(blob["distance_residuals"])


# README table, "OpenMVG 2.1 global SfM ...": geodesic metric / as evalQuality reports it
README_MEANS = {"fountain-P11": (0.0364, 0.0471), "Herz-Jesus-P8": (0.0258, 0.0726), "entry-P10": (0.0438, 0.0873)}


@pytest.mark.parametrize("scene", SCENES)
def test_matches_readme_table_means(scene):
    scene_dir = FIXTURES / scene
    report = quality.evaluate(_read_strecha(scene_dir),
                              _read_sfm_data(scene_dir / "openmvg" / "global" / "sfm_data.json"))
    geodesic, evalquality = README_MEANS[scene]
    assert report.rotation_error_deg.mean == pytest.approx(geodesic, abs=5e-5)
    assert report.evalquality.angular_residual_deg.mean == pytest.approx(evalquality, abs=5e-5)


# ---------------------------------------------------------------- report files

def test_report_files_and_contract_fields(tmp_path):
    scene_dir = FIXTURES / "Herz-Jesus-P8"
    report = quality.evaluate(_read_strecha(scene_dir),
                              _read_sfm_data(scene_dir / "openmvg" / "global" / "sfm_data.json"))
    report.gt_path, report.estimate_path = "gt/dir", "est/sfm_data.json"
    out = write_report(report, tmp_path / "report")
    data = json.loads((out / "report.json").read_text())
    assert data["num_gt"] == 8 and data["num_estimated"] == 8
    assert set(data["rotation_error_deg"]) >= {"min", "max", "mean", "median"}
    assert set(data["position_error"]) >= {"min", "max", "mean", "median"}
    assert len(data["per_camera"]) == 8 and data["per_camera"][0]["name"] == "0000.jpg"
    assert data["evalquality"]["angular_residual_deg"]["mean"] == pytest.approx(0.0726, abs=5e-5)
    page = (out / "report.html").read_text()
    assert "est/sfm_data.json" in page and "0007.jpg" in page
    for png in ("per_camera_rotation.png", "per_camera_position.png", "cumulative_errors.png", "top_view.png"):
        assert f'src="{png}"' in page
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]  # no temp dir left behind
    table = format_table(report)
    assert "evalQuality angular residual" in table and "0.0726" in table

    # rewriting over a previous report works; a foreign non-empty directory is refused
    write_report(report, out)
    foreign = tmp_path / "project"
    foreign.mkdir()
    (foreign / "sfm_data.json").write_text("{}")
    with pytest.raises(InputError):
        write_report(report, foreign)
    assert (foreign / "sfm_data.json").read_text() == "{}"


# ---------------------------------------------------------------- `rotonly eval` CLI

def _run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    from rotonly_cli.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


@pytest.fixture
def minimal_readers(monkeypatch):
    """Route the CLI's lazy reader look-up to this file's minimal parsers (format detection,
    exit codes and output handling are what these CLI tests check; the real readers have their
    own tests and the end-to-end test below)."""
    from rotonly_cli.io import detect

    readers = {("strecha", "read_strecha_dir"): lambda p: _read_strecha_minimal(
                   Path(p) if (Path(p) / "gt_dense_cameras").is_dir() else Path(p).parent),
               ("openmvg", "read_sfm_data"): lambda p, poses_only=False: _read_sfm_data_minimal(Path(p))}
    monkeypatch.setattr(detect, "_reader", lambda module, name: readers[(module, name)])


def test_cli_writes_report_and_prints_table(tmp_path, capsys, minimal_readers):
    scene_dir = FIXTURES / "entry-P10"
    out = tmp_path / "rep"
    code, stdout, _ = _run_cli(["eval", "--gt", str(scene_dir), str(scene_dir / "openmvg/global/sfm_data.json"),
                                "-o", str(out)], capsys)
    assert code == 0
    assert "matched 10" in stdout and "0.0873" in stdout  # evalQuality mean angle of the README
    assert json.loads((out / "report.json").read_text())["num_matched"] == 10
    # gt_dense_cameras/ itself is accepted as GT too; --json puts exactly the JSON on stdout
    code, stdout, stderr = _run_cli(["eval", "--gt", str(scene_dir / "gt_dense_cameras"),
                                     str(scene_dir / "openmvg/global/sfm_data.json"), "-o", str(out), "--json"], capsys)
    assert code == 0
    data = json.loads(stdout)
    assert data["rotation_error_deg"]["mean"] == pytest.approx(0.0438, abs=5e-5)
    assert "matched 10" in stderr


@pytest.mark.parametrize("case", ["missing_gt", "missing_estimate", "no_common", "bad_folder"])
def test_cli_bad_input_exits_2_with_one_line_and_no_output(tmp_path, capsys, minimal_readers, case):
    scene_dir = FIXTURES / "fountain-P11"
    estimate = scene_dir / "openmvg/global/sfm_data.json"
    gt = scene_dir
    if case == "missing_gt":
        gt = tmp_path / "nope"
    elif case == "missing_estimate":
        estimate = tmp_path / "nope.json"
    elif case == "no_common":
        data = json.loads(estimate.read_text())
        for entry in data["views"]:
            data_of_view = entry["value"]["ptr_wrapper"]["data"]
            data_of_view["filename"] = "other_" + data_of_view["filename"]
        estimate = tmp_path / "renamed.json"
        estimate.write_text(json.dumps(data))
    elif case == "bad_folder":
        estimate = tmp_path / "empty_dir"
        estimate.mkdir()
    out = tmp_path / "rep"
    code, stdout, stderr = _run_cli(["eval", "--gt", str(gt), str(estimate), "-o", str(out)], capsys)
    assert code == 2
    assert len(stderr.strip().splitlines()) == 1 and stderr.startswith("error: ")
    assert "Traceback" not in stderr
    assert not out.exists()
    assert not any(p.name.startswith(".rep.") for p in tmp_path.iterdir())


def test_cli_end_to_end_with_project_readers(tmp_path, capsys):
    """`rotonly eval` through the real readers (io/strecha.py, io/openmvg/)."""
    pytest.importorskip("rotonly_cli.io.strecha")
    pytest.importorskip("rotonly_cli.io.openmvg")
    scene_dir = FIXTURES / "fountain-P11"
    blob = json.loads((scene_dir / "openmvg/eval/gt_eval_stats_blob.json").read_text())
    out = tmp_path / "rep"
    code, stdout, _ = _run_cli(["eval", "--gt", str(scene_dir), str(scene_dir / "openmvg/global/sfm_data.json"),
                                "-o", str(out), "--json"], capsys)
    assert code == 0
    data = json.loads(stdout)
    np.testing.assert_allclose(data["evalquality"]["rotation_angular_residuals"], blob["rotation_angular_residuals"],
                               rtol=0, atol=1e-4)
    np.testing.assert_allclose(data["evalquality"]["distance_residuals"], blob["distance_residuals"], rtol=1e-3)
    assert data["rotation_error_deg"]["mean"] == pytest.approx(0.0364, abs=5e-5)
    assert (out / "report.html").is_file()


def test_cli_colmap_model_as_estimate_and_as_gt(tmp_path, capsys):
    """A COLMAP model (written by io/colmap.py from the OpenMVG fixture) is read on either side."""
    colmap_io = pytest.importorskip("rotonly_cli.io.colmap")
    openmvg_io = pytest.importorskip("rotonly_cli.io.openmvg")
    scene_dir = FIXTURES / "entry-P10"
    model_dir = tmp_path / "model"
    colmap_io.write_model(model_dir, openmvg_io.read_sfm_data(scene_dir / "openmvg/global/sfm_data.json"))
    blob = json.loads((scene_dir / "openmvg/eval/gt_eval_stats_blob.json").read_text())
    code, stdout, _ = _run_cli(["eval", "--gt", str(scene_dir), str(model_dir), "-o", str(tmp_path / "a"), "--json"],
                               capsys)
    assert code == 0
    np.testing.assert_allclose(json.loads(stdout)["evalquality"]["rotation_angular_residuals"],
                               blob["rotation_angular_residuals"], rtol=0, atol=1e-4)
    code, stdout, _ = _run_cli(["eval", "--gt", str(model_dir), str(scene_dir / "openmvg/global/sfm_data.json"),
                                "-o", str(tmp_path / "b"), "--json"], capsys)
    assert code == 0
    assert json.loads(stdout)["rotation_error_deg"]["max"] == pytest.approx(0.0, abs=1e-9)
