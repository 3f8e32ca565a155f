"""Stage `translate`: the baseline check of LiGT's centres against the edges' own translation
directions reaches the run's report and summary (and stays silent on real clean data)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import rotonly_cli
from rotonly_cli.stages import translate

from helpers import DATA_FIXTURES

DATABASE = DATA_FIXTURES / "herzjesu_p8" / "database.db"


def test_clean_fixture_passes_the_baseline_check():
    result = rotonly_cli.run(DATABASE, progress=False)
    baselines = result.reports["translate"]["baselines"]
    assert baselines["views_off"] == {}
    assert baselines["num_edges"] >= 10 and baselines["angle_deg"]["max"] < 5.0
    assert not any(w.startswith("positions") for w in result.summary["warnings"])


def test_a_collapsed_solve_is_reported_and_warned(monkeypatch, tmp_path):
    """LiGT made to collapse (every centre shrunk to its centroid but the first view's, thrown
    far out): the run names that view in reports/translate.json and warns in the summary."""
    solve = translate.robust_ligt_translations

    def collapsing(*args, **kwargs):
        robust = solve(*args, **kwargs)
        centers = robust.result.centers
        collapsed = centers.mean(axis=0) + 1e-3 * (centers - centers.mean(axis=0))
        collapsed[0] = centers[0] + 50.0 * np.ptp(centers, axis=0).max() * np.array([0.3, 0.8, 0.5])
        return replace(robust, result=replace(robust.result, centers=collapsed))

    monkeypatch.setattr(translate, "robust_ligt_translations", collapsing)
    result = rotonly_cli.run(DATABASE, tmp_path / "out", progress=False)
    first_view = sorted(result.rotations)[0]
    off = result.reports["translate"]["baselines"]["views_off"]
    assert list(off) == [str(first_view)] and off[str(first_view)] > 10.0
    warnings = [w for w in result.summary["warnings"] if w.startswith("positions")]
    assert len(warnings) == 1 and f"{first_view} (" in warnings[0]
    assert "positions" in (tmp_path / "out" / "run.log").read_text()
    report = (tmp_path / "out" / "report.html").read_text()
    assert 'id="warnings"' in report and "positions may have collapsed" in report


def test_the_robust_rounds_take_a_helper_process_only_from_the_measured_size_on(monkeypatch):
    """LiGT's helper process slowed the Strecha-sized translate stages (docs/tuning.md): with
    --jobs 2 and parts of 1000 matches (GRRM's helper runs) the fixture's observations stay in
    one process; with the threshold at their number the helper runs, and the centres are the
    same bits."""
    from rotonly_cli.runtime import parallel

    def translate_report():
        result = rotonly_cli.run(DATABASE, progress=False, jobs=2)
        return result.reports, np.stack([result.centers[v] for v in sorted(result.centers)])

    monkeypatch.setattr(parallel, "MIN_MATCHES_PER_JOB", 1000)
    reports, centers_one = translate_report()
    one = reports["translate"]
    assert reports["optimize"]["processes"] == 2 and one["processes"] == 1
    assert one["num_observations"] < translate.LIGT_HELPER_MIN_OBSERVATIONS
    monkeypatch.setattr(translate, "LIGT_HELPER_MIN_OBSERVATIONS", one["num_observations"])
    reports, centers_two = translate_report()
    two = reports["translate"]
    assert two["processes"] == 2
    np.testing.assert_array_equal(centers_two, centers_one)
