"""scripts/bench/strecha_tools.py, tool_runs.py and scale.py on small fixtures / simulated scenes."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.geometry import so3
from rotonly_cli.scene.types import Pose, SfMScene, View

from helpers import DATA_FIXTURES, REPOSITORY

ROOT = REPOSITORY
FIXTURES = DATA_FIXTURES


def _load_script(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_script_{name}", ROOT / "scripts" / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


bench_strecha = _load_script("strecha_tools")
#: the tool runs strecha_tools imported (it put scripts/bench on sys.path): one module, so that a patch reaches it
bench_tools = sys.modules["tool_runs"]
bench_scale = _load_script("scale")


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _gt_scene(rng: np.random.Generator, n: int) -> SfMScene:
    scene = SfMScene(source="test")
    for v in range(n):
        scene.views[v] = View(v, f"{v:04d}.jpg", 0)
        scene.poses[v] = Pose(so3.random_rotations(1, rng)[0], rng.normal(size=3))
    return scene


# ============================================================================ bench_strecha pieces

def test_pycolmap_rotation_averaging_recovers_exact_rotations_both_weightings():
    """The reference bench_tools.pycolmap_ra_results calls, with the inlier counts it passes."""
    from rotonly_cli.baselines.references import pycolmap_rotation_averaging

    rng = np.random.default_rng(3)
    R = so3.random_rotations(6, rng)
    i, j = np.triu_indices(6, k=1)
    R_j_from_i = R[j] @ np.swapaxes(R[i], -1, -2)
    for weighted in (False, True):
        R_est = pycolmap_rotation_averaging(6, np.column_stack([i, j]), R_j_from_i,
                                            num_matches=np.arange(15) + 30, weighted=weighted)
        relative = R_est[j] @ np.swapaxes(R_est[i], -1, -2)
        assert np.degrees(so3.geodesic_angle(relative, R_j_from_i)).max() < 1e-4


def test_evaluate_scene_rotation_only_and_with_centres():
    rng = np.random.default_rng(4)
    gt = _gt_scene(rng, 5)
    S = so3.random_rotations(1, rng)[0]
    names = {v: gt.views[v].name for v in gt.views}
    exact = bench_tools.rotations_scene(names, {v: gt.poses[v].R_cam_from_world @ S for v in gt.views})
    result = bench_tools.evaluate_scene("exact", gt, exact, 1.5)
    assert result.rotation_mean_deg < 1e-6 and result.position_mean is None  # zero centres: rotation-only
    assert (result.num_registered, result.num_gt, result.time_s) == (5, 5, 1.5)

    # one camera 1° off about its own axis, centres a similarity of the GT
    R_off = {v: gt.poses[v].R_cam_from_world @ S for v in gt.views}
    R_off[2] = so3.exp(np.radians(1.0) * np.array([0.0, 0.0, 1.0])) @ R_off[2]
    centers = {v: 2.0 * S.T @ gt.poses[v].center + 1.0 for v in gt.views}
    del R_off[4]
    result = bench_tools.evaluate_scene("off", gt, bench_tools.rotations_scene(names, R_off, centers), None)
    assert result.num_registered == 4
    assert result.position_mean < 1e-9
    assert 0.2 < result.rotation_mean_deg < 0.5  # 1° spread over 4 cameras by the L2 alignment
    assert bench_tools.evaluate_scene("none", gt, SfMScene(), None).error == "no pose estimated"


def _fixture_root(tmp_path: Path) -> tuple[Path, list[Path]]:
    """A Strecha-like ROOT with one scene made of links to the Herz-Jesu fixtures."""
    scene = tmp_path / "root" / "Herz-Jesus-P8"
    (scene / "openmvg" / "global").mkdir(parents=True)
    source = FIXTURES / "herzjesu_p8"
    inputs = [source / "database.db", *sorted((source / "openmvg").iterdir()),
              FIXTURES / "evalquality" / "Herz-Jesus-P8" / "openmvg" / "global" / "sfm_data.json"]
    (scene / "database.db").symlink_to(inputs[0])
    (scene / "gt_dense_cameras").symlink_to(source / "gt_dense_cameras")
    for path in inputs[1:-1]:
        (scene / "openmvg" / path.name).symlink_to(path)
    (scene / "openmvg" / "global" / "sfm_data.json").symlink_to(inputs[-1])
    return tmp_path / "root", inputs


def test_bench_strecha_end_to_end_on_fixture(tmp_path, capsys):
    root, inputs = _fixture_root(tmp_path)
    before = {path: _digest(path) for path in inputs}
    out = tmp_path / "results"
    assert bench_strecha.main(["--root", str(root), "-o", str(out), "--skip-mapper"]) == 0
    assert {path: _digest(path) for path in inputs} == before  # inputs untouched
    assert sorted(p.name for p in out.iterdir()) == ["logs", "results.json", "table.md"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary leftovers

    rows = {r["method"]: r for r in json.loads((out / "results.json").read_text())["scenes"]["Herz-Jesus-P8"]}
    for method, row in rows.items():
        assert not row["error"], (method, row["error"])
        assert row["num_registered"] == row["num_gt"] == 8, method
    run_db = rows["rotonly run database.db"]
    assert run_db["rotation_mean_deg"] < 0.1 and run_db["position_mean"] < 0.05
    assert set(run_db["extra"]["stage_times_s"]) >= {"load", "optimize", "triangulate", "run"}
    assert 0.0 < run_db["extra"]["subprocess_cpu_s"] < 10 * run_db["time_s"]
    # the subprocess run and the in-process stages are the same deterministic chain
    for label, run_method in (("database.db", "rotonly run database.db"),
                              ("openmvg", "rotonly run openmvg/sfm_data.json")):
        in_process = rows[f"rotonly GRRM, in-process ({label})"]
        assert abs(in_process["rotation_mean_deg"] - rows[run_method]["rotation_mean_deg"]) < 1e-6
        assert rows[f"rotonly L1-IRLS average = GRRM start ({label})"]["position_mean"] is None
    # the stored OpenMVG global result is the real one: the README's Herz-Jesu number
    openmvg_row = rows["OpenMVG 2.1 global SfM (LiGT + BA, stored result)"]
    assert abs(openmvg_row["rotation_mean_deg"] - 0.0258) < 5e-4 and openmvg_row["time_s"] == 1.0
    # the BA reference starts from each rotonly run's own model and moves it (K fixed)
    for label, run_method in (("database.db", "rotonly run database.db"),
                              ("openmvg", "rotonly run openmvg/sfm_data.json")):
        ba = rows[f"reference: pycolmap BA (K fixed) started from rotonly's model ({label})"]
        assert ba["rotation_mean_deg"] < 0.1 and ba["position_mean"] < 0.05 and ba["time_s"] > 0
        assert abs(ba["rotation_mean_deg"] - rows[run_method]["rotation_mean_deg"]) > 1e-6
    stored = rows["pycolmap RA on the stored two-view geometries"]
    assert 0.0 < stored["rotation_mean_deg"] < 1.0 and stored["extra"]["num_edges"] > 0

    table = (out / "table.md").read_text()
    assert "### Herz-Jesus-P8" in table and "### Summary" in table
    assert table.count("| rotonly run ") >= 4  # per-scene rows, stage-time rows
    assert "### Summary" in capsys.readouterr().out


def test_bench_strecha_refuses_results_inside_root(tmp_path):
    root, _ = _fixture_root(tmp_path)
    with pytest.raises(SystemExit) as exc:
        bench_strecha.main(["--root", str(root), "-o", str(root / "results")])
    assert exc.value.code == 2
    assert not (root / "results").exists()


# ============================================================================ bench_scale pieces

def test_peak_rss_probe_sees_a_200_mb_buffer_after_reset():
    from rotonly_cli import monitor

    resettable = monitor.reset_peak_rss()
    base = monitor.peak_rss_mb()
    buffer = np.ones(25_000_000)  # 200 MB, touched
    assert monitor.peak_rss_mb() > base + 150
    del buffer
    if resettable:
        monitor.reset_peak_rss()
        assert monitor.peak_rss_mb() < base + 150


def test_bench_scale_on_a_small_simulated_collection(tmp_path, monkeypatch):
    """The whole `rotonly run` and the global mapper as processes on one simulated database:
    both register every view, rotonly's per-stage figures come from its resources.json."""
    monkeypatch.setitem(bench_scale.RECIPES, "tiny", "--setup circular --views 8 --points 500 --window 3 --seed 1")
    md = tmp_path / "results.md"
    assert bench_scale.main(["--recipes", "tiny", "--cache", str(tmp_path / "in"), "-o", str(tmp_path / "out"),
                             "--results-md", str(md)]) == 0
    row = json.loads((tmp_path / "out" / "results.json").read_text())[0]
    assert row["counts"]["images"] == 8 and row["counts"]["matches"] > 1000
    for method in ("rotonly", "mapper"):
        assert row[method]["exit"] == 0 and row[method]["registered"] == 8, row[method]
        assert 0.0 < row[method]["rotation_mean_deg"] < 0.5 and row[method]["peak_rss_mb"] > 50
    assert set(row["rotonly"]["stages"]) == set(bench_scale.STAGES)
    assert all(stage["time_s"] > 0 and stage["peak_rss_mb"] > 50 for stage in row["rotonly"]["stages"].values())
    text = md.read_text()
    assert "| tiny | 8 |" in text and "rotonly run" in text and "pycolmap global mapper" in text


def _fake_openmvg_tools(folder: Path, result_json: Path) -> Path:
    """Stand-ins for openMVG_main_SfM (writes <output_dir>/sfm_data.bin, prints OpenMVG's timing
    line) and openMVG_main_ConvertSfM_DataFormat (copies -i to -o): the glue is what is tested."""
    folder.mkdir()
    sfm = folder / "openMVG_main_SfM"
    sfm.write_text(f"#!{sys.executable}\nimport shutil, sys\nout = sys.argv[sys.argv.index('--output_dir') + 1]\n"
                   f"import os; os.makedirs(out)\nshutil.copyfile({str(result_json)!r}, out + '/sfm_data.bin')\n"
                   "open(out + '/argv.txt', 'w').write(' '.join(sys.argv[1:]))\n"
                   "print('INFO: [main_SfM.cpp:618]  Total Sfm took (s): 3')\n")
    convert = folder / "openMVG_main_ConvertSfM_DataFormat"
    convert.write_text(f"#!{sys.executable}\nimport shutil, sys\na = sys.argv\n"
                       "shutil.copyfile(a[a.index('-i') + 1], a[a.index('-o') + 1])\n")
    for tool in (sfm, convert):
        tool.chmod(0o755)
    return folder


def test_openmvg_global_rerun_is_timed_converted_and_evaluated(tmp_path: Path):
    """--openmvg-bin: OpenMVG's global SfM runs on a copy of the project (ROOT untouched), its
    process wall time and its own "Total Sfm took" line are kept, its result is evaluated."""
    from dataclasses import replace

    from rotonly_cli.io import detect, openmvg

    scene_dir = FIXTURES / "herzjesu_p8"
    gt = detect.read_ground_truth(scene_dir)
    result_scene = replace(gt, intrinsics={k: replace(v, model="pinhole", params=v.params[[0, 2, 3]])
                                           for k, v in gt.intrinsics.items()})
    openmvg.write_sfm_data(tmp_path / "result.json", result_scene)
    tools = _fake_openmvg_tools(tmp_path / "bin", tmp_path / "result.json")
    assert bench_tools.check_openmvg_bin(tools) is None
    assert "openMVG_main_SfM" in bench_tools.check_openmvg_bin(tmp_path)
    before = {p.name: _digest(p) for p in (scene_dir / "openmvg").iterdir()}
    (tmp_path / "work").mkdir()
    (tmp_path / "logs").mkdir()
    result = bench_tools.run_openmvg_global(scene_dir / "openmvg", gt, tools, tmp_path / "work", tmp_path / "logs")
    assert result.error == ""
    assert result.num_registered == 8 and result.rotation_mean_deg < 1e-6
    assert result.extra["openmvg_reported_s"] == 3.0 and 0 < result.time_s < 30
    assert result.time_note.startswith("subprocess wall")
    assert (tmp_path / "work" / "openmvg_project" / "matches.e.bin").is_file()
    assert "-f" not in (tmp_path / "work" / "openmvg_global" / "argv.txt").read_text().split()
    held = bench_tools.run_openmvg_global(scene_dir / "openmvg", gt, tools, tmp_path / "work", tmp_path / "logs",
                                            hold_intrinsics=True)
    assert held.error == "" and "intrinsics held" in held.method and held.method != result.method
    assert (tmp_path / "work" / "openmvg_global_held_k" / "argv.txt").read_text().endswith("-f NONE")
    assert {p.name: _digest(p) for p in (scene_dir / "openmvg").iterdir()} == before

    (tools / "openMVG_main_SfM").write_text("#!/bin/sh\necho 'cannot open matches' >&2\nexit 3\n")
    failed = bench_tools.run_openmvg_global(scene_dir / "openmvg", gt, tools, tmp_path / "work2", tmp_path / "logs")
    assert failed.error.startswith("exit 3") and "cannot open matches" in failed.error


def test_alternating_runs_rotate_the_order_and_report_failures(tmp_path: Path):
    log = tmp_path / "order.txt"

    def command(name):
        return lambda k: [sys.executable, "-c", f"open({str(log)!r}, 'a').write('{name}{k} '); print('{name}{k}')"]

    runs = bench_tools.alternating_runs({"a": command("a"), "b": command("b")}, 3)
    assert log.read_text().split() == ["a0", "b0", "b1", "a1", "a2", "b2"]
    assert [[out.strip() for _, out in runs[n]] for n in "ab"] == [["a0", "a1", "a2"], ["b0", "b1", "b2"]]
    assert all(t > 0 for v in runs.values() for t, _ in v)
    failing = {"a": command("a"), "bad": lambda k: [sys.executable, "-c", "import sys; sys.exit('no matches')"]}
    with pytest.raises(RuntimeError, match="bad: exit 1: .*no matches"):
        bench_tools.alternating_runs(failing, 2)


def test_openmvg_input_timing_runs_both_tools_on_one_copy(tmp_path: Path):
    """--timing-rounds: the real `rotonly -q run` and (here a stand-in) OpenMVG's global SfM
    on one copy of the project, alternating; medians, their ratio and the table line."""
    scene_dir = FIXTURES / "herzjesu_p8"
    tools = _fake_openmvg_tools(tmp_path / "bin", tmp_path / "unused.json")
    (tools / "openMVG_main_SfM").write_text(f"#!{sys.executable}\nimport os, sys, time\n"
                                            "os.makedirs(sys.argv[sys.argv.index('--output_dir') + 1])\n"
                                            "time.sleep(0.2)\n")
    before = {p.name: _digest(p) for p in (scene_dir / "openmvg").iterdir()}
    (tmp_path / "work").mkdir()
    timing = bench_tools.openmvg_input_timing(scene_dir / "openmvg", tools, tmp_path / "work", 2)
    assert {p.name: _digest(p) for p in (scene_dir / "openmvg").iterdir()} == before
    assert timing["rounds"] == 2 and len(timing["rotonly_s"]) == len(timing["reference_s"]) == 2
    assert min(timing["reference_s"]) >= 0.2 and min(timing["rotonly_s"]) > 0.3  # a real rotonly run
    assert timing["ratio_of_medians"] == pytest.approx(timing["median_rotonly_s"] / timing["median_reference_s"])
    assert (tmp_path / "work" / "rotonly_timing" / "sfm_data.json").is_file()
    row = bench_tools.MethodResult("rotonly run openmvg/sfm_data.json", time_s=1.0,
                                     extra={"alternating_timing": timing})
    lines = bench_strecha.ratio_lines([row])
    assert any(line.startswith("- 2 alternating rounds, rotonly run openmvg/sfm_data.json / OpenMVG")
               and f"{timing['ratio_of_medians']:.2f}x" in line for line in lines)
    failed = bench_strecha.ratio_lines([bench_tools.MethodResult(
        "rotonly run openmvg/sfm_data.json", time_s=1.0, extra={"alternating_timing": {"error": "boom"}})])
    assert "- alternating wall times of rotonly run openmvg/sfm_data.json failed: boom" in failed


def test_database_timing_compares_with_the_mapper_call_and_process(tmp_path: Path, monkeypatch):
    """The database rounds: rotonly's wall time against the mapper worker's global_mapping call
    (its JSON line) and its process wall; each mapper round gets its own database copy."""
    database = FIXTURES / "herzjesu_p8" / "database.db"
    seen = {}

    def fake_runs(commands, rounds):
        seen.update({name: [make(k) for k in range(rounds)] for name, make in commands.items()})
        calls = [4.0, 6.0, 5.0]
        return {"rotonly": [(1.0, ""), (1.5, ""), (1.2, "")],
                "mapper": [(c + 1.0, json.dumps({"call_s": c, "num_models": 1}) + "\n") for c in calls]}

    monkeypatch.setattr(bench_tools, "alternating_runs", fake_runs)
    (tmp_path / "work").mkdir()
    timing = bench_tools.database_timing(database, tmp_path / "work", 2, 3)
    assert timing["median_rotonly_s"] == 1.2 and timing["median_reference_s"] == 5.0
    assert timing["ratio_of_medians"] == pytest.approx(1.2 / 5.0)
    assert timing["ratio_to_process_medians"] == pytest.approx(1.2 / 6.0)
    assert timing["reference_time"] == "global_mapping call, 2 threads"
    mapper_argv = seen["mapper"][-1]
    assert "--mapper-worker" in mapper_argv and mapper_argv[-2:] == ["2", "0"]
    copy = Path(mapper_argv[mapper_argv.index("--mapper-worker") + 1])
    assert copy.parent.parent == tmp_path / "work" and _digest(copy) == _digest(database)
    assert seen["rotonly"][0][-4:] == ["run", str(database), "-o", str(tmp_path / "work" / "rotonly_db_timing")]
    line = bench_strecha.ratio_lines([bench_tools.MethodResult("rotonly run database.db", time_s=1.0,
                                                                 extra={"alternating_timing": timing})])[-1]
    assert line.startswith("- 3 alternating rounds, rotonly run database.db / pycolmap global mapper")
    assert "**0.24x**" in line and "0.20x of its process wall" in line


def test_global_mapper_runs_as_a_process_and_both_times_are_kept(tmp_path):
    """The pycolmap global mapper reference runs in a child process: its call time is time_s
    (the data README's measure), its whole process wall time is extra, and ratio_lines
    reports rotonly's wall time over both."""
    from rotonly_cli.io import detect

    scene_dir = FIXTURES / "herzjesu_p8"
    gt = detect.read_ground_truth(scene_dir)
    before = _digest(scene_dir / "database.db")
    mapper = bench_tools.run_global_mapper(scene_dir / "database.db", gt, threads=2)
    assert _digest(scene_dir / "database.db") == before
    assert mapper.error == "" and mapper.num_registered == 8 and mapper.rotation_mean_deg < 0.1
    assert 0.0 < mapper.time_s < mapper.extra["process_wall_s"]
    ours = bench_tools.MethodResult("rotonly run database.db", time_s=mapper.time_s / 4)
    lines = bench_strecha.ratio_lines([ours, mapper])
    assert len(lines) == 2 and "0.25x (global_mapping call" in lines[1]
    assert f"{mapper.time_s / 4 / mapper.extra['process_wall_s']:.2f}x of its process wall" in lines[1]


def test_guessed_focal_bench_gives_every_image_its_camera(tmp_path: Path):
    """--camera-per-image: the same database as COLMAP's extractor leaves it by default."""
    from rotonly_cli.io import colmap

    sys.path.insert(0, str(ROOT / "scripts" / "bench"))
    try:
        guessed_focal = _load_script("guessed_focal")
    finally:
        sys.path.remove(str(ROOT / "scripts" / "bench"))
    source = FIXTURES / "herzjesu_p8" / "database.db"
    before = _digest(source)
    given = colmap.read_database(source)
    rewritten = colmap.read_database(guessed_focal.camera_per_image(source, tmp_path / "per_image.db"))
    assert _digest(source) == before
    assert len(given.intrinsics) == 1 and len(rewritten.intrinsics) == len(rewritten.views) == len(given.views)
    assert sorted({view.intrinsics_id for view in rewritten.views.values()}) == sorted(rewritten.intrinsics)
    for view_id, view in rewritten.views.items():
        camera = rewritten.intrinsics[view.intrinsics_id]
        original = given.intrinsics[given.views[view_id].intrinsics_id]
        assert (camera.model, camera.params.tolist(), camera.prior_focal) == \
            (original.model, original.params.tolist(), original.prior_focal)
        np.testing.assert_array_equal(rewritten.keypoints[view_id], given.keypoints[view_id])
    assert sorted(rewritten.pairs) == sorted(given.pairs)
    for key, pair in given.pairs.items():
        np.testing.assert_array_equal(rewritten.pairs[key].matches, pair.matches)
        assert rewritten.pairs[key].config == pair.config
