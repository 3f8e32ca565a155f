"""`rotonly run` and the stage subcommands through the CLI, on the bundled Strecha fixtures
(data_fixtures/<scene>/: COLMAP database and OpenMVG project with 1000-inlier subsets)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.cli import main
from rotonly_cli.io import colmap

from helpers import DATA_FIXTURES

FIXTURES = DATA_FIXTURES
HERZ_JESU = FIXTURES / "herzjesu_p8"
FOUNTAIN = FIXTURES / "fountain_p11"


def _rotonly(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    return exit_info.value.code


@pytest.fixture(scope="module")
def herzjesu_run(tmp_path_factory):
    """One `rotonly run` of the Herz-Jesu fixture database with --gt, shared by the tests."""
    root = tmp_path_factory.mktemp("hj")
    db = root / "database.db"
    shutil.copyfile(HERZ_JESU / "database.db", db)
    out = root / "out"
    code = _rotonly("-q", "run", db, "-o", out, "--gt", HERZ_JESU)
    return code, db, out


def check_openmvg_writer_rules(path: Path) -> dict:
    """The rules OpenMVG's loader enforces (formats.md §1.1-§1.9, §6)."""
    document = json.loads(path.read_text())
    assert list(document) == ["sfm_data_version", "root_path", "views", "intrinsics", "extrinsics", "structure",
                              "control_points"]
    assert document["sfm_data_version"] == "0.3"
    views, intrinsics = document["views"], document["intrinsics"]
    ptr_ids = [item["value"]["ptr_wrapper"]["id"] for item in views + intrinsics]
    assert ptr_ids == list(range(2147483649, 2147483649 + len(ptr_ids)))
    view_data = [item["value"]["ptr_wrapper"]["data"] for item in views]
    for data in view_data:
        for key in ("width", "height", "id_view", "id_intrinsic", "id_pose"):
            assert type(data[key]) is int, key
    pose_ids = {data["id_pose"] for data in view_data}
    extrinsic_ids = [item["key"] for item in document["extrinsics"]]
    assert set(extrinsic_ids) <= pose_ids  # ValidIds: no orphan pose (§1.9)
    assert {item["key"] for item in intrinsics} <= {data["id_intrinsic"] for data in view_data}
    for item in document["extrinsics"]:
        R = np.array(item["value"]["rotation"])
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    posed = set(extrinsic_ids)
    for landmark in document["structure"][:200]:
        observations = landmark["value"]["observations"]
        assert len(observations) >= 2
        assert all(o["key"] in posed and type(o["value"]["id_feat"]) is int for o in observations)
    return document


def test_run_colmap_fixture_outputs(herzjesu_run):
    code, _, out = herzjesu_run
    assert code == 0
    for name in ("sfm_data.json", "view_graph.json", "run.log", "state.npz", "eval/report.json", "eval/report.html"):
        assert (out / name).is_file(), name
    document = check_openmvg_writer_rules(out / "sfm_data.json")
    assert len(document["extrinsics"]) == 8 and len(document["structure"]) > 5000

    import pycolmap

    model = pycolmap.Reconstruction(str(out / "sparse"))
    assert model.num_reg_images() == 8
    assert model.num_points3D() == len(document["structure"])
    # measured 0.31 px; rotation-only poses, no bundle adjustment
    assert model.compute_mean_reprojection_error() < 1.0

    graph = json.loads((out / "view_graph.json").read_text())
    assert len(graph["edges"]) == 28  # every verified pair, with its status
    sources = {e["pose_source"] for e in graph["edges"]}
    assert sources == {"stored", "ransac"}  # PLANAR/UNCALIBRATED pairs were re-estimated
    assert all(e["config"] == "CALIBRATED" for e in graph["edges"] if e["pose_source"] == "stored")
    assert "done in" in (out / "run.log").read_text()


def test_run_colmap_fixture_rotation_error_band(herzjesu_run):
    _, _, out = herzjesu_run
    report = json.loads((out / "eval" / "report.json").read_text())
    assert report["num_gt"] == 8 and report["num_estimated"] == 8
    # measured: mean 0.0189°, max 0.031° (README: OpenMVG global SfM 0.026°, pycolmap global 0.019°
    # on the full data; this fixture keeps 1000 inliers per pair)
    assert report["rotation_error_deg"]["mean"] < 0.035
    assert report["rotation_error_deg"]["max"] < 0.06


def test_run_database_written_by_colmap_3_8(tmp_path):
    """A database written by COLMAP 3.8 itself (Debian's colmap; scripts/fixtures/make_colmap38_fixture.py):
    the 3.8 schema, and all-zero qvec/tvec because 3.8 does not compute relative poses by
    default, so every CALIBRATED edge is re-estimated. The input is left byte for byte."""
    import sqlite3

    db = tmp_path / "database.db"
    shutil.copyfile(FIXTURES / "colmap38_herzjesu4" / "database.db", db)
    with sqlite3.connect(db) as connection:  # the fixture is what it says it is
        tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        image_columns = {row[1] for row in connection.execute("PRAGMA table_info(images)")}
        qvecs = [bytes(row[0]) for row in connection.execute("SELECT qvec FROM two_view_geometries")]
    assert "frames" not in tables and "rigs" not in tables and "prior_qw" in image_columns
    assert len(qvecs) == 6 and all(not np.frombuffer(q).any() for q in qvecs)
    before = db.read_bytes()
    out = tmp_path / "out"
    assert _rotonly("-q", "run", db, "-o", out, "--gt", HERZ_JESU) == 0
    assert db.read_bytes() == before
    graph = json.loads((out / "view_graph.json").read_text())
    assert [(e["config"], e["pose_source"], e["status"]) for e in graph["edges"]] == \
        [("CALIBRATED", "ransac", "active")] * 6
    report = json.loads((out / "eval" / "report.json").read_text())
    # measured: mean 0.0193 deg, max 0.029 deg on these 4 images (0.0181 deg on all 8 from COLMAP 3.8)
    assert report["num_estimated"] == 4
    assert report["rotation_error_deg"]["mean"] < 0.035


def test_same_input_twice_and_stage_by_stage_give_identical_sfm_data(herzjesu_run, tmp_path):
    _, db, out = herzjesu_run
    assert _rotonly("-q", "run", db, "-o", tmp_path / "again") == 0
    assert (tmp_path / "again" / "sfm_data.json").read_bytes() == (out / "sfm_data.json").read_bytes()

    workspace = tmp_path / "staged"
    assert _rotonly("-q", "identify", db, "-o", workspace) == 0
    assert not (workspace / "sfm_data.json").exists()
    # 28 pairs: one below --min-inliers in the input, one after the stable consensus
    assert json.loads((workspace / "reports" / "identify.json").read_text())["kinds"]["REGULAR"] == 26
    assert _rotonly("-q", "optimize", workspace) == 2  # refine and average not done yet
    for stage in ("refine", "average", "optimize", "translate", "reject", "triangulate"):
        assert _rotonly("-q", stage, workspace) == 0, stage
    assert (workspace / "sfm_data.json").read_bytes() == (out / "sfm_data.json").read_bytes()


def test_run_openmvg_fixture(tmp_path):
    out = tmp_path / "out"
    code = _rotonly("-q", "run", FOUNTAIN / "openmvg" / "sfm_data.json", "-o", out, "--gt", FOUNTAIN)
    assert code == 0
    check_openmvg_writer_rules(out / "sfm_data.json")
    report = json.loads((out / "eval" / "report.json").read_text())
    assert report["num_estimated"] == 11
    # measured: mean 0.0262°, max 0.039° (OpenMVG matches, every pose re-estimated by RANSAC)
    assert report["rotation_error_deg"]["mean"] < 0.04
    assert report["rotation_error_deg"]["max"] < 0.07
    graph = json.loads((out / "view_graph.json").read_text())
    # OpenMVG stores no relative poses: every edge with enough matches was re-estimated
    assert [(e["pose_source"], e["status"]) for e in graph["edges"] if e["reason"] != "too few inliers"] == \
        [("ransac", "active")] * 51
    few = [e for e in graph["edges"] if e["reason"] == "too few inliers"]
    assert all(e["num_inliers"] < 30 for e in few) and len(few) == 4
    # two were short in the input, two lost RANSAC outliers and unstable matches below 30
    assert sum(bool(e["dropped_matches"]) for e in few) == 2
    assert all(set(e["dropped_matches"]) <= {"RANSAC outlier", "unstable consensus", "minority keypoint of its track"}
               for e in graph["edges"])
    assert colmap.read_model(out / "sparse").poses.keys() == set(range(1, 12))  # 0-based views shifted +1


def test_bad_input_exit_2_one_line_nothing_written(tmp_path, capsys):
    bad = tmp_path / "broken.db"
    bad.write_text("SQLite? no")
    assert _rotonly("run", bad, "-o", tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and str(bad) in err[-1] and "Traceback" not in "\n".join(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.db"]


def test_bad_gt_fails_before_the_chain_runs(tmp_path, capsys, monkeypatch):
    """A mistyped --gt is reported at once (exit 2, nothing written), not after the whole
    chain, whose result would be thrown away with the failed run."""
    from rotonly_cli import pipeline

    def no_chain(*args, **kwargs):
        raise AssertionError("the chain ran before --gt was checked")

    monkeypatch.setattr(pipeline, "load_stage", no_chain)
    for gt in (tmp_path / "missing", tmp_path):  # does not exist / is no GT at all
        assert _rotonly("run", HERZ_JESU / "database.db", "-o", tmp_path / "out", "--gt", gt) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("error: ") and "--gt" in err[-1] and str(gt) in err[-1]
        assert list(tmp_path.iterdir()) == []


def test_bad_gt_of_a_stage_command_fails_before_the_stage(herzjesu_run, tmp_path, capsys, monkeypatch):
    """`rotonly triangulate OUT --gt GT` checks GT the same way, before the stage runs."""
    from rotonly_cli import pipeline

    def no_stage(run):
        raise AssertionError("the stage ran before --gt was checked")

    _, _, out = herzjesu_run
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    monkeypatch.setitem(pipeline.STAGE_FUNCTIONS, "triangulate", no_stage)
    assert _rotonly("triangulate", out, "--gt", tmp_path / "missing") == 2
    assert "--gt" in capsys.readouterr().err.strip().splitlines()[-1]
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_bad_input_is_reported_before_scipy_is_imported():
    """`rotonly run` checks INPUT and OUT before the numerical stages: importing the CLI
    command and the pipeline must not import scipy (~0.3 s, half of a bad-input exit)."""
    import subprocess
    import sys

    code = ("import sys; import rotonly_cli.cli.run, rotonly_cli.pipeline; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'pycolmap', 'cv2', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_fewer_than_two_usable_images_exit_1(tmp_path, capsys):
    # the fixture with --min-inliers above every pair's inlier count: no edge survives
    assert _rotonly("run", HERZ_JESU / "database.db", "-o", tmp_path / "out", "--min-inliers", "100000") == 1
    assert "fewer than two usable images" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and list(tmp_path.iterdir()) == []


def test_colmap_input_gives_openmvg_ids_in_file_name_order(tmp_path):
    """OpenMVG's evalQuality pairs cameras by pose id: the sfm_data.json written from a
    COLMAP database numbers views 0..n-1 in file-name order (as SfMInit_ImageListing does)."""
    import json

    from rotonly_cli.pipeline import run_pipeline

    out = tmp_path / "out"
    run_pipeline(FIXTURES / "herzjesu_p8" / "database.db", out)
    doc = json.loads((out / "sfm_data.json").read_text())
    views = sorted((v["key"], v["value"]["ptr_wrapper"]["data"]["filename"],
                    v["value"]["ptr_wrapper"]["data"]["id_pose"]) for v in doc["views"])
    names = [name for _, name, _ in views]
    assert names == sorted(names)
    assert all(key == pose for key, _, pose in views)
    # every landmark observation still points at the right image after renumbering: the
    # points reproject onto their stored observation pixels
    from rotonly_cli.io import openmvg

    scene = openmvg.read_sfm_data(out / "sfm_data.json")
    assert len(scene.poses) == 8
    errors = []
    for obs, X, pixels in list(zip(scene.structure.observations, scene.structure.points,
                                   scene.structure.observation_pixels))[:300]:
        for (view_id, _), pixel in zip(obs, pixels):
            pose = scene.poses[view_id]
            focal, ppx, ppy = scene.intrinsics[scene.views[view_id].intrinsics_id].params[:3]
            x = pose.R_cam_from_world @ (X - pose.center)
            errors.append(np.linalg.norm(focal * x[:2] / x[2] + [ppx, ppy] - pixel))
    assert np.median(errors) < 1.0


def test_console_script_freezes_objects_before_shutdown_and_keeps_the_exit_code(monkeypatch, capsys, tmp_path):
    """The installed `rotonly` is console.main, which runs cli.console_main: main, then gc.freeze
    before interpreter shutdown (skips its full collection, ~0.2 s a run); exit codes are main's.
    main alone, which the tests call in-process, freezes nothing."""
    import gc
    import importlib.metadata

    from rotonly_cli import cli

    (entry,) = [e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == "rotonly"]
    assert entry.value == "rotonly_cli.console:main"
    frozen = []
    monkeypatch.setattr(gc, "freeze", lambda: frozen.append(True))
    for argv, code in ((["rotonly", "--version"], 0), (["rotonly", "no-such-command"], 2),
                       (["rotonly", "run", str(tmp_path / "missing.db"), "-o", str(tmp_path / "out")], 2)):
        monkeypatch.setattr("sys.argv", argv)
        with pytest.raises(SystemExit) as exit_info:
            cli.console_main()
        assert exit_info.value.code == code and frozen == [True], argv
        frozen.clear()
    with pytest.raises(SystemExit):
        cli.main(["--version"])
    assert frozen == [] and not (tmp_path / "out").exists()
    capsys.readouterr()
