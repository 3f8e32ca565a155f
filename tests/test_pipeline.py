"""pipeline / stages on small synthetic scenes: accuracy, components, failures, atomic OUT."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.evaluation.quality import evaluate
from rotonly_cli.geometry import so3
from rotonly_cli.io import colmap, openmvg
from rotonly_cli.options import LoadOptions
from rotonly_cli.pipeline import RunOptions, resume, run_pipeline
from rotonly_cli.scene.types import View
from rotonly_cli.scene.view_graph import Edge, ViewGraph
from rotonly_cli.simulation.layout_scenes import simulate_multiview
from rotonly_cli.stages.average import OUTLIER_REASON, AverageOptions, average_graph


def _problem(seed: int = 1, num_views: int = 10):
    # a street of cameras, 0.5 px noise, stored relative rotations 0.5° off the truth
    return simulate_multiview("linear", num_views=num_views, num_points=1500, noise_px=0.5, rng=seed,
                              init="perturbed", init_noise_deg=0.5, window=4, min_shared=30)


def _write_db(tmp_path: Path, problem, name: str = "database.db") -> Path:
    path = tmp_path / name
    colmap.write_database(path, problem.scene)
    return path


def _rotation_errors(problem, out_dir: Path):
    estimate = openmvg.read_sfm_data(out_dir / "sfm_data.json")
    return evaluate(problem.gt_scene(), estimate)


def test_synthetic_run_recovers_rotations(tmp_path):
    problem = _problem()
    db = _write_db(tmp_path, problem)
    # the stored rotations are kept (no RANSAC), so that TRRM has the 0.5° to undo
    summary = run_pipeline(db, tmp_path / "out", RunOptions(load=LoadOptions(reestimate="none")))
    assert summary["num_registered"] == 10 and summary["unregistered_views"] == []
    report = _rotation_errors(problem, tmp_path / "out")
    assert report.num_matched == 10
    # measured 0.0067° mean / 0.012° max (seeds 5, 9: 0.0043-0.0060 / 0.007-0.016) from stored
    # rotations 0.5° off at 0.5 px noise: TRRM + averaging + GRRM remove the init error
    assert report.rotation_error_deg.mean < 0.015
    assert report.rotation_error_deg.max < 0.03
    assert report.position_error.max < 0.08  # GT units after the similarity; measured 0.038 (spacing 10)
    # every stage wrote its report; reports hold real numbers
    for stage in ("load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate", "run"):
        assert (tmp_path / "out" / "reports" / f"{stage}.json").is_file(), stage
    refine = json.loads((tmp_path / "out" / "reports" / "refine.json").read_text())
    assert refine["cost_after"] < refine["cost_before"]
    assert refine["rotation_change_deg"]["median"] > 0.1  # the 0.5° perturbation was undone


def _split_problem(seed: int, first: int):
    """The street of 10 views with every pair between views 0..first-1 and first..9 cut."""
    problem = _problem(seed=seed)
    problem.scene.pairs = {key: pair for key, pair in problem.scene.pairs.items()
                           if (key[0] < first) == (key[1] < first)}
    return problem


def test_the_input_is_detected_once_per_run(tmp_path, monkeypatch):
    """run_into detects INPUT's kind once and hands it down: the memory count, the reader
    (io/readers.READERS) and the load report use it."""
    from rotonly_cli import pipeline
    from rotonly_cli.io import detect
    from rotonly_cli.stages import load

    calls = []

    def counted(path):
        calls.append(path)
        return detect.detect_input(path)

    monkeypatch.setattr(pipeline, "detect_input", counted)
    monkeypatch.setattr(load, "detect_input", counted)
    database = _write_db(tmp_path, _problem(num_views=5))
    run_pipeline(database, tmp_path / "out", RunOptions(jobs=1), stages=("load", "identify"))
    assert calls == [database]


def test_disconnected_graph_writes_each_component_as_a_model(tmp_path):
    import pycolmap

    problem = _split_problem(seed=2, first=6)  # two components of 6 and 4 views
    db = _write_db(tmp_path, problem)
    out = tmp_path / "out"
    summary = run_pipeline(db, out, RunOptions())
    # COLMAP image ids are view ids + 1; the largest component is the model of sparse/ as before
    assert summary["num_registered"] == 6
    assert summary["unregistered_views"] == []  # the other 4 are in a model of their own
    graph = json.loads((out / "view_graph.json").read_text())
    assert graph["unregistered_views"] == [7, 8, 9, 10]  # the largest component's view graph, as before
    outside = [e for e in graph["edges"] if e["i"] >= 7]
    assert outside and all(e["reason"] == "outside largest component" for e in outside)
    main, other = summary["components"]
    assert (main["model"], main["num_views"], main["num_registered"]) == ("sparse", 6, 6)
    assert (other["model"], other["sfm_data"]) == ("sparse/1", "sfm_data.component1.json")
    assert (other["views"], other["num_registered"]) == ([7, 8, 9, 10], 4)
    assert other["num_points"] > 1000  # measured 1365 (main: 1382)
    assert json.loads((out / "reports" / "run.json").read_text())["components"] == summary["components"]
    for model, images, points in (("sparse", [1, 2, 3, 4, 5, 6], main["num_points"]),
                                  ("sparse/1", [7, 8, 9, 10], other["num_points"])):
        reconstruction = pycolmap.Reconstruction(str(out / model))
        assert sorted(reconstruction.reg_image_ids()) == images
        assert reconstruction.num_points3D() == points
    assert _rotation_errors(problem, out).num_matched == 6
    component = evaluate(problem.gt_scene(), openmvg.read_sfm_data(out / "sfm_data.component1.json"))
    assert component.num_matched == 4
    assert component.rotation_error_deg.max < 0.05  # measured 0.0095
    assert "sfm_data.component1.json" in (out / "report.html").read_text()
    # a second run replaces the workspace with its component files
    run_pipeline(db, out, RunOptions())
    assert (out / "sparse" / "1" / "images.bin").is_file()
    # a stage command rewrites the main model only: the other models, now stale, go
    resumed = resume(out, "triangulate")
    assert [c["model"] for c in resumed["components"]] == ["sparse"] and resumed["components"][0]["num_views"] == 6
    assert not (out / "sparse" / "1").exists() and not (out / "sfm_data.component1.json").exists()
    assert pycolmap.Reconstruction(str(out / "sparse")).num_reg_images() == 6


def test_component_of_two_views_is_not_written_and_a_warning_says_so(tmp_path):
    problem = _split_problem(seed=2, first=8)  # components of 8 and 2 views
    out = tmp_path / "out"
    summary = run_pipeline(_write_db(tmp_path, problem), out, RunOptions())
    assert summary["num_registered"] == 8 and summary["unregistered_views"] == [9, 10]
    assert [c["model"] for c in summary["components"]] == ["sparse", None]
    assert summary["components"][1]["reason"] == "2 views (a model needs 3)"
    assert any("not written as models: views 9, 10: 2 views" in w for w in summary["warnings"])
    assert not (out / "sparse" / "1").exists()
    assert not list(out.glob("sfm_data.component*.json"))


def test_fewer_than_two_usable_images_exits_1_and_leaves_nothing(tmp_path):
    problem = _problem(seed=3, num_views=4)
    first = sorted(problem.scene.pairs)[0]
    pair = problem.scene.pairs[first]
    pair.matches = pair.matches[:20]  # below --min-inliers 30
    problem.scene.pairs = {first: pair}
    db = _write_db(tmp_path, problem)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(AlgorithmError, match="fewer than two usable images"):
        run_pipeline(db, tmp_path / "out", RunOptions())
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no OUT, no temp folder left


def test_failed_run_keeps_previous_workspace_untouched(tmp_path):
    problem = _problem(seed=4, num_views=5)
    db = _write_db(tmp_path, problem)
    run_pipeline(db, tmp_path / "out", RunOptions())
    before = (tmp_path / "out" / "sfm_data.json").read_bytes()
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"not a database at all")
    with pytest.raises(InputError):
        run_pipeline(bad, tmp_path / "out", RunOptions())
    assert (tmp_path / "out" / "sfm_data.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.db", "database.db", "out"]


def test_out_with_foreign_files_is_refused(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "thesis.tex").write_text("precious")
    with pytest.raises(InputError, match="not a rotonly workspace"):
        run_pipeline(tmp_path / "whatever.db", tmp_path / "out", RunOptions())
    assert (tmp_path / "out" / "thesis.tex").read_text() == "precious"


def _consistent_graph(num_views: int, rng: np.random.Generator):
    R = so3.random_rotations(num_views, rng)
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 0) for v in range(num_views)})
    for i in range(num_views):
        for j in range(i + 1, min(i + 4, num_views)):
            noise = so3.exp(rng.normal(scale=np.radians(0.05), size=3))
            graph.edges.append(Edge(i, j, noise @ R[j] @ R[i].T, np.zeros(3),
                                    np.zeros((100, 2), dtype=np.int64)))
    return R, graph


def test_average_filters_gross_outlier_edges_and_solves_again():
    rng = np.random.default_rng(7)
    R_true, graph = _consistent_graph(8, rng)
    bad = [3, 10]
    for k in bad:  # repeated-structure-like errors: 30° and 90°
        angle = 30.0 if k == 3 else 90.0
        graph.edges[k].R_j_from_i = so3.exp(np.radians(angle) * np.array([0.0, 1.0, 0.0])) @ graph.edges[k].R_j_from_i
    R, report = average_graph(graph, AverageOptions(max_residual_deg=5.0))
    assert [k for k, e in enumerate(graph.edges) if not e.active] == bad
    assert all(graph.edges[k].reason == OUTLIER_REASON for k in bad)
    assert report["num_outliers_filtered"] == 2 and len(report["rounds"]) == 2
    S = R[0].T @ R_true[0]
    errors = np.degrees(so3.geodesic_angle(R @ S, R_true))
    assert errors.max() < 0.1  # noise 0.05° per edge
