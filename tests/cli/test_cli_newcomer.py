"""What a new user meets first (issue 52, "tried as a new user would"): the help says what the
defaults do, a folder holding a database points at it, a ground truth of another scene is
warned about, and no library chatter or progress bars land where they do not belong."""

from __future__ import annotations

import re

import pytest

from rotonly_cli.cli import main

from helpers import DATA_FIXTURES

HERZ_JESU = DATA_FIXTURES / "herzjesu_p8"


def _rotonly(capsys, *args) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def _flat(text: str) -> str:
    """Help text with click's line wrapping undone."""
    return re.sub(r"\s+", " ", text.replace("-\n", "-"))


def test_run_help_describes_the_default_reestimate(capsys):
    from rotonly_cli.options import LoadOptions, Reestimate

    assert LoadOptions.reestimate == Reestimate.ALL
    code, out, _ = _rotonly(capsys, "run", "--help")
    text = _flat(out)
    assert code == 0
    assert "every edge re-estimated by calibrated RANSAC; --reestimate auto keeps stored E-based ones" in text
    assert "all = every edge" in text and "[default: all]" in text
    assert "stored E-based ones kept, others re-estimated" not in text


def test_a_camera_without_an_openmvg_twin_is_a_debug_line_naming_its_colmap_id(caplog):
    """A PINHOLE camera with fx != fy is written to sfm_data.json as OpenMVG's one-focal pinhole,
    its keypoints placed for it (nothing lost): a -v line, numbered as the summary numbers it
    (COLMAP's camera 1), not an info line of every COLMAP run naming a "camera 0"."""
    import logging

    from rotonly_cli.io import colmap

    scene = colmap.read_database(HERZ_JESU / "database.db")
    assert scene.intrinsics[1].model == "PINHOLE" and scene.intrinsics[1].params[0] != scene.intrinsics[1].params[1]
    with caplog.at_level(logging.DEBUG, logger="rotonly_cli"):
        colmap.colmap_to_openmvg(scene)
    lines = [r for r in caplog.records if r.name == "rotonly_cli.io.colmap.cameras"]
    assert lines and all(r.levelno == logging.DEBUG for r in lines)
    assert lines[0].getMessage().startswith("camera 1 (PINHOLE) in sfm_data.json: OpenMVG's pinhole f=")
    assert "the same rays" in lines[0].getMessage()


def test_first_report_on_a_machine_prints_no_font_cache_line(tmp_path):
    """matplotlib builds its font cache on the first figure of a machine and logs "generated
    new fontManager" at info level: rotonly's output shows the library's warnings only."""
    import os
    import subprocess
    import sys

    gt = DATA_FIXTURES / "evalquality" / "entry-P10"
    code = ("from rotonly_cli.cli import main; "
            f"main(['eval', '--gt', {str(gt)!r}, {str(gt / 'openmvg/global/sfm_data.json')!r}, "
            f"'-o', {str(tmp_path / 'eval')!r}])")
    env = {**os.environ, "MPLCONFIGDIR": str(tmp_path / "fresh_matplotlib")}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert any((tmp_path / "fresh_matplotlib").iterdir())  # the font cache was built by this run
    assert "fontManager" not in result.stderr and "font" not in result.stderr.lower(), result.stderr


@pytest.mark.parametrize("command", ["run", "convert"])
def test_a_folder_holding_a_database_points_at_it(tmp_path, capsys, command):
    folder = tmp_path / "project"
    folder.mkdir()
    (folder / "database.db").write_bytes((HERZ_JESU / "database.db").read_bytes())
    code, _, err = _rotonly(capsys, command, folder, "-o", tmp_path / "out")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert err.strip().endswith(f"; it holds a COLMAP database: give {folder / 'database.db'}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["project"]
    # another name is suggested when it is the folder's only database; two others, none
    (folder / "database.db").rename(folder / "scene.db")
    assert _rotonly(capsys, command, folder, "-o", tmp_path / "out")[2].strip().endswith(
        f"give {folder / 'scene.db'}")
    (folder / "other.db").write_bytes((folder / "scene.db").read_bytes())
    assert "COLMAP database" not in _rotonly(capsys, command, folder, "-o", tmp_path / "out")[2]


def test_gt_of_another_scene_is_warned_about(tmp_path, capsys):
    """Herz-Jesu's database against fountain-P11's ground truth: the names 0000-0007.jpg match
    8 of its 11 cameras and the errors are tens of degrees. The run still succeeds (the result is
    fine), with a warning on the terminal, in run.log, reports/run.json and report.html."""
    import json

    out = tmp_path / "out"
    other = DATA_FIXTURES / "evalquality" / "fountain-P11"
    code, stdout, _ = _rotonly(capsys, "-q", "run", HERZ_JESU / "database.db", "-o", out, "--gt", other)
    assert code == 0
    expected = ("--gt: 3 of the 11 GT cameras name none of the input's images: is the GT this scene's? The errors "
                "cover the 8 images matched by name")
    assert f"warning: {expected}" in stdout.splitlines()
    assert expected in json.loads((out / "reports" / "run.json").read_text())["warnings"]
    assert expected in (out / "run.log").read_text()
    assert expected.replace("'", "&#x27;") in (out / "report.html").read_text()


def test_eval_warns_when_few_cameras_match(tmp_path, capsys):
    estimate = DATA_FIXTURES / "evalquality" / "Herz-Jesus-P8" / "openmvg" / "global" / "sfm_data.json"
    code, _, err = _rotonly(capsys, "eval", "--gt", DATA_FIXTURES / "evalquality" / "fountain-P11", estimate,
                            "-o", tmp_path / "other")
    assert code == 0
    assert err.strip().splitlines() == [
        "warning: 3 of the 11 GT cameras have no estimated pose: is the GT this scene's? The errors cover the 8 "
        "images matched by name"]
    code, _, err = _rotonly(capsys, "eval", "--gt", DATA_FIXTURES / "evalquality" / "Herz-Jesus-P8", estimate,
                            "-o", tmp_path / "same")
    assert code == 0 and "warning" not in err


def test_unmatched_share_that_warns():
    from rotonly_cli.evaluation.quality import unmatched_warning

    def report(gt: int, matched: int, extra: int) -> dict:
        return {"num_gt": gt, "num_matched": matched, "missing_in_estimate": [f"{k}.jpg" for k in range(matched, gt)],
                "not_in_gt": [f"x{k}.jpg" for k in range(extra)]}

    assert unmatched_warning(report(19, 19, 0)) is None
    assert unmatched_warning(report(20, 18, 2)) is None  # a tenth on either side: no warning
    assert unmatched_warning(report(8, 8, 1)) is None  # one image more than the GT (a still frame): none
    assert unmatched_warning(report(19, 11, 0)) == ("8 of the 19 GT cameras have no estimated pose: is the GT this "
                                                    "scene's? The errors cover the 11 images matched by name")
    assert unmatched_warning(report(11, 11, 8)).startswith("8 of the 19 posed images are not in the GT: ")
    assert unmatched_warning(report(19, 11, 3)).startswith("8 of the 19 GT cameras have no estimated pose and 3 of "
                                                           "the 14 posed images are not in the GT: ")
    # a GT camera whose image was given but not registered is not another scene's (its own warning says so)
    assert unmatched_warning(report(19, 11, 0), input_names=[f"{k}.jpg" for k in range(19)]) is None
    assert unmatched_warning(report(19, 11, 0), input_names=[f"images/{k}.jpg" for k in range(19)]) is None


def test_consensus_fast_is_the_agreeing_runs_of_the_load_stage(capsys, tmp_path):
    """--consensus maps to LoadOptions.consensus_agreement and agreement_min_edges (fast: the
    agreeing runs on any load; full: off; auto, the default: from AUTO_AGREEMENT_MIN_EDGES edges
    on) in the CLI and the API alike, and a bad value names the option."""
    import json

    from rotonly_cli.errors import InputError
    from rotonly_cli.options import LoadOptions, RunOptions
    from rotonly_cli.options.inputs import AUTO_AGREEMENT_MIN_EDGES, FAST_CONSENSUS_AGREEMENT
    from rotonly_cli.options.settings import with_settings

    auto = (FAST_CONSENSUS_AGREEMENT, AUTO_AGREEMENT_MIN_EDGES)
    assert (LoadOptions().consensus_agreement, LoadOptions().agreement_min_edges) == auto
    fast = with_settings(RunOptions(), {"consensus": "fast"})
    assert (fast.load.consensus_agreement, fast.load.agreement_min_edges) == (FAST_CONSENSUS_AGREEMENT, 0)
    assert with_settings(fast, {"consensus": "full"}).load.consensus_agreement is None
    back = with_settings(with_settings(fast, {"consensus": "full"}), {"consensus": "auto"}).load
    assert (back.consensus_agreement, back.agreement_min_edges) == auto
    with pytest.raises(InputError, match="consensus"):
        with_settings(RunOptions(), {"consensus": "quick"})
    # five views, a pair of each adjacent two holding ~2500 matches (the fixtures hold 1000 at most)
    code, _, err = _rotonly(capsys, "-q", "simulate", "multiview", "--setup", "circular", "--views", "5", "--points",
                            "4000", "--window", "1", "--init", "perturbed", "--format", "colmap",
                            "-o", tmp_path / "sim")
    assert code == 0, err
    runs = {}
    for mode in ("full", "fast"):
        out = tmp_path / mode
        code, _, err = _rotonly(capsys, "-q", "identify", tmp_path / "sim" / "database.db", "-o", out, "--consensus",
                                mode)
        assert code == 0, err
        report = json.loads((out / "reports" / "load.json").read_text())
        runs[mode] = report["ransac_runs"], report["num_reestimated"]
    (full_runs, edges), (fast_runs, _) = runs["full"], runs["fast"]
    assert full_runs == LoadOptions.consensus_runs * edges  # every edge's four runs
    # an edge of more than 1000 matches whose first two runs agree stops there (most of these clean pairs)
    assert 2 * edges <= fast_runs <= full_runs - 2 * (edges // 2)
    code, _, err = _rotonly(capsys, "identify", HERZ_JESU / "database.db", "-o", tmp_path / "bad", "--consensus", "x")
    assert code == 2 and "--consensus" in err and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("stage", ["optimize", "translate", "reject", "triangulate"])
def test_stage_commands_use_the_cpus_as_run_does(capsys, monkeypatch, tmp_path, stage):
    """GRRM and LiGT run in two processes under `rotonly run`; the stage commands that run them
    take --jobs with the same default (the usable CPUs), not one process."""
    from rotonly_cli import pipeline
    from rotonly_cli.runtime.parallel import usable_cpus

    jobs = []

    def resume(workspace, name, options):
        jobs.append((name, options.jobs))
        return {"stages": [name], "num_active_edges": 0, "time_s": 0.0}

    monkeypatch.setattr(pipeline, "resume", resume)
    assert _rotonly(capsys, "-q", stage, tmp_path)[0] == 0
    assert _rotonly(capsys, "-q", stage, tmp_path, "--jobs", "3")[0] == 0
    assert jobs == [(stage, usable_cpus()), (stage, 3)]
