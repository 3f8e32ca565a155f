"""`rotonly simulate twoview|multiview` and `rotonly refine FILE.npz` end to end (CliRunner)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rotonly_cli.cli import cli, main
from rotonly_cli.simulation.pair_scenes import load_twoview


def test_simulate_twoview_writes_reproducible_npz(tmp_path) -> None:
    runner = CliRunner()
    args = ["simulate", "twoview", "--scene", "holoplane", "--noise", "0.5", "--points", "120", "--seed", "4"]
    result = runner.invoke(cli, args + ["-o", str(tmp_path / "a.npz")])
    assert result.exit_code == 0, result.output
    assert "scene=holoplane points=120" in result.output
    runner.invoke(cli, args + ["-o", str(tmp_path / "b.npz")])
    a, b = load_twoview(tmp_path / "a.npz"), load_twoview(tmp_path / "b.npz")
    assert a.scene == "holoplane" and a.num_points == 120 and a.noise_px == 0.5 and a.seed == 4
    np.testing.assert_array_equal(a.x_j, b.x_j)
    noise_px = np.linalg.norm(a.x_i - a.x_i_true, axis=1) * a.focal
    assert 0.0 < noise_px.max() <= 0.5


def test_refine_rejects_non_npz(tmp_path, capsys) -> None:
    (tmp_path / "workspace").mkdir()
    with pytest.raises(SystemExit) as exit_info:
        main(["refine", str(tmp_path / "workspace")])
    assert exit_info.value.code == 2
    assert "TARGET" in capsys.readouterr().err


def test_refine_missing_file_exit_2(tmp_path, capsys) -> None:
    pytest.importorskip("rotonly_cli.twoview")
    with pytest.raises(SystemExit) as exit_info:
        main(["refine", str(tmp_path / "missing.npz")])
    assert exit_info.value.code == 2
    assert "missing.npz" in capsys.readouterr().err


@pytest.mark.parametrize("init", ["ransac", "truth-perturbed"])
def test_simulate_then_refine_standard(tmp_path, init: str) -> None:
    pytest.importorskip("rotonly_cli.twoview")
    runner = CliRunner()
    path = tmp_path / "edge.npz"
    result = runner.invoke(cli, ["simulate", "twoview", "--scene", "standard", "--noise", "1", "--points", "400",
                                 "--seed", "2", "-o", str(path)])
    assert result.exit_code == 0, result.output
    result = runner.invoke(cli, ["refine", str(path), "--init", init, "--perturb-deg", "1.0", "--json"])
    assert result.exit_code == 0, result.output
    row = json.loads(result.output)
    assert row["kind"] == "REGULAR"
    assert row["detection_value"] > 1e-3  # standard scene: far above the 1e-4 RotationSingular threshold
    if init == "truth-perturbed":
        assert abs(row["initial_rotation_error_deg"] - 1.0) < 1e-9
    # TRRM lands at the noise level (~0.1 deg at 1 px, 400 points) and beats the start
    assert row["refined_rotation_error_deg"] < 0.3
    assert row["refined_rotation_error_deg"] < row["initial_rotation_error_deg"]
    assert row["refined_translation_error_deg"] < 5.0
    table = runner.invoke(cli, ["refine", str(path), "--init", init])
    assert "rotation error (deg)" in table.output and "REGULAR" in table.output


def _refine_json(tmp_path, scene: str) -> dict:
    runner = CliRunner()
    path = tmp_path / f"{scene}.npz"
    runner.invoke(cli, ["simulate", "twoview", "--scene", scene, "--noise", "0.5", "--points", "300",
                        "--seed", "1", "-o", str(path)])
    result = runner.invoke(cli, ["refine", str(path), "--init", "truth-perturbed", "--perturb-deg", "0.2", "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.output)


def test_refine_line_scene_is_rotation_singular(tmp_path) -> None:
    pytest.importorskip("rotonly_cli.twoview")
    row = _refine_json(tmp_path, "rankregular_line")
    assert row["detection_value"] < 1e-4  # paper §Scene Identification threshold
    assert row["kind"] == "ROTATION_SINGULAR"
    assert row["refined_rotation_error_deg"] == pytest.approx(row["initial_rotation_error_deg"])  # Alg. 2: left as is


def test_refine_holoplane_is_rotation_singular(tmp_path) -> None:
    pytest.importorskip("rotonly_cli.twoview")
    row = _refine_json(tmp_path, "holoplane")  # rank P^S = 1: points and both centres on one plane
    assert row["detection_value"] < 1e-4
    assert row["kind"] == "ROTATION_SINGULAR"
    assert row["refined_rotation_error_deg"] == pytest.approx(row["initial_rotation_error_deg"])


def test_simulate_multiview_writes_projects(tmp_path) -> None:
    pytest.importorskip("rotonly_cli.io.colmap")
    pytest.importorskip("rotonly_cli.io.openmvg")
    runner = CliRunner()
    out = tmp_path / "mv"
    result = runner.invoke(cli, ["simulate", "multiview", "--setup", "circular", "--views", "8", "--points", "400",
                                 "--window", "2", "--min-shared", "10", "--corrupt-fraction", "0.2",
                                 "--seed", "3", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert (out / "database.db").is_file() and (out / "gt" / "sfm_data.json").is_file()
    assert (out / "openmvg" / "sfm_data.json").is_file()
    info = json.loads((out / "simulation.json").read_text())
    assert info["setup"] == "circular" and len(info["corrupted_pairs"]) == round(0.2 * info["num_pairs"])
    gt = json.loads((out / "gt" / "sfm_data.json").read_text())
    assert len(gt["views"]) == 8 and len(gt["extrinsics"]) == 8
    # a second run into the same (now non-empty) folder is refused without touching it
    again = runner.invoke(cli, ["simulate", "multiview", "--views", "8", "--points", "400", "-o", str(out)])
    assert again.exit_code != 0
