"""`rotonly eval` as a regression gate (evaluation/gate.py): absolute limits and a baseline
report.json with a tolerance; a crossed limit exits 3 with one line naming the metric, its
value and the limit, after writing the report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rotonly_cli.errors import InputError, RegressionError
from rotonly_cli.evaluation import gate

from helpers import DATA_FIXTURES

SCENE = DATA_FIXTURES / "evalquality" / "entry-P10"
ESTIMATE = SCENE / "openmvg" / "global" / "sfm_data.json"
ROTATION_MEAN = 0.043806  # this estimate's mean geodesic rotation error (deg), 6 digits
POSITION_MEAN = 0.00744192  # its mean centre error after the similarity (GT units)


def _eval(capsys, out: Path, *limits) -> tuple[int, str, str]:
    from rotonly_cli.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--gt", str(SCENE), str(ESTIMATE), "-o", str(out), *map(str, limits)])
    stdout, stderr = capsys.readouterr()
    return exit_info.value.code, stdout, stderr


@pytest.fixture(scope="module")
def report() -> dict:
    from rotonly_cli.evaluation.quality import evaluate
    from rotonly_cli.io.detect import read_scene

    data = evaluate(read_scene(SCENE, field="--gt"), read_scene(ESTIMATE, ground_truth=False)).to_dict()
    assert f"{data['rotation_error_deg']['mean']:.6g}" == f"{ROTATION_MEAN:.6g}"
    assert f"{data['position_error']['mean']:.6g}" == f"{POSITION_MEAN:.6g}"
    assert data["num_matched"] == 10
    return data


def _baseline(tmp_path: Path, report: dict, rotation_scale: float = 1.0, registered: int | None = None) -> Path:
    """A baseline report.json: ``report`` whose mean rotation error is ``rotation_scale`` times its own."""
    old = json.loads(json.dumps(report))
    old["rotation_error_deg"]["mean"] *= rotation_scale
    if registered is not None:
        old["num_matched"] = registered
    path = tmp_path / "baseline" / "report.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(old))
    return path


def test_every_limit_held_exits_0_and_says_so(tmp_path, capsys, report):
    baseline = _baseline(tmp_path, report)
    code, stdout, stderr = _eval(capsys, tmp_path / "eval", "--max-rotation-deg", 0.05, "--max-position", 0.01,
                                 "--min-registered", 10, "--baseline", baseline, "--tolerance", "10%")
    assert code == 0, stderr
    assert "matched 10" in stdout
    (held,) = [line for line in stderr.splitlines() if line.startswith("limits held: ")]
    assert f"rotation error mean {ROTATION_MEAN:g} deg <= limit 0.05 deg (--max-rotation-deg)" in held
    assert "registered GT cameras 10 >= limit 10 (--min-registered)" in held
    assert held.count("(--baseline: ") == 3
    # no limits: no gate line, exit 0 as ever
    code, _, stderr = _eval(capsys, tmp_path / "eval")
    assert code == 0 and "limits held" not in stderr


@pytest.mark.parametrize("option, limit, line", [
    ("--max-rotation-deg", 0.04, f"rotation error mean {ROTATION_MEAN:g} deg > limit 0.04 deg (--max-rotation-deg)"),
    ("--max-position", 0.005,
     f"position error mean {POSITION_MEAN:g} GT units > limit 0.005 GT units (--max-position)"),
    ("--min-registered", 11, "registered GT cameras 10 < limit 11 (--min-registered)"),
])
def test_each_limit_crossed_exits_3_with_one_line(tmp_path, capsys, option, limit, line):
    code, stdout, stderr = _eval(capsys, tmp_path / "eval", option, limit)
    assert code == 3
    assert stderr.strip().splitlines() == [f"error: regression: {line}"]
    assert "matched 10" in stdout  # the table is printed and the report written before the verdict
    assert json.loads((tmp_path / "eval" / "report.json").read_text())["num_matched"] == 10
    assert (tmp_path / "eval" / "report.html").is_file()


def test_two_limits_crossed_share_the_line(tmp_path, capsys):
    code, _, stderr = _eval(capsys, tmp_path / "eval", "--max-rotation-deg", 0.01, "--min-registered", 11,
                            "--max-position", 1.0)
    assert code == 3
    (line,) = stderr.strip().splitlines()
    assert line.startswith("error: regression: rotation error mean ") and "; registered GT cameras 10 < " in line
    assert "position" not in line  # a limit held is not named


def test_baseline_within_and_beyond_the_tolerance(tmp_path, capsys, report):
    # the error grew by 5 % since the baseline: within 10 %
    code, _, stderr = _eval(capsys, tmp_path / "a", "--baseline", _baseline(tmp_path, report, 1 / 1.05),
                            "--tolerance", "10%")
    assert code == 0, stderr
    # grown by 20 %: beyond the default 10 %, within 0.25
    beyond = _baseline(tmp_path, report, 1 / 1.2)
    code, _, stderr = _eval(capsys, tmp_path / "b", "--baseline", beyond)
    assert code == 3
    old = ROTATION_MEAN / 1.2
    (line,) = stderr.strip().splitlines()
    assert line == (f"error: regression: rotation error mean {ROTATION_MEAN:g} deg > limit {old * 1.1:.6g} deg "
                    f"(--baseline: {old:.6g} deg + 10%)")
    assert _eval(capsys, tmp_path / "c", "--baseline", beyond, "--tolerance", "0.25")[0] == 0
    # the baseline's folder (eval's -o) is taken too; fewer registered cameras than it had fail
    code, _, stderr = _eval(capsys, tmp_path / "d", "--baseline", _baseline(tmp_path, report, registered=11).parent)
    assert code == 3
    assert stderr.strip() == "error: regression: registered GT cameras 10 < limit 11 (--baseline: as many)"


def test_json_stays_on_stdout_when_the_gate_fails(tmp_path, capsys):
    code, stdout, stderr = _eval(capsys, tmp_path / "eval", "--json", "--max-rotation-deg", 0.01)
    assert code == 3
    assert json.loads(stdout)["num_matched"] == 10
    assert stderr.strip().splitlines()[-1].startswith("error: regression: rotation error mean")


@pytest.mark.parametrize("limits, message", [
    (["--tolerance", "10%"], "--tolerance needs --baseline"),
    (["--baseline", "{tmp}/missing.json"], "--baseline: no such file"),
    (["--baseline", "{tmp}"], "no report.json in it or in its eval/"),
    (["--baseline", "{tmp}/not_a_report.json"], "no number rotation_error_deg.mean"),
    (["--baseline", "{tmp}/not_a_report.json", "--tolerance", "10"], "write 10% for percent"),
    (["--max-rotation-deg", "-1"], "--max-rotation-deg"),
    (["--max-position", "nan"], "--max-position"),
])
def test_bad_limits_exit_2_before_anything_is_written(tmp_path, capsys, limits, message):
    (tmp_path / "not_a_report.json").write_text('{"num_gt": 3}')
    code, _, stderr = _eval(capsys, tmp_path / "eval", *[arg.format(tmp=tmp_path) for arg in limits])
    assert code == 2
    assert len(stderr.strip().splitlines()) == 1 and message in stderr
    assert not (tmp_path / "eval").exists()


def test_exit_codes_are_in_the_help(capsys):
    from rotonly_cli.cli import main

    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3 accuracy regression: a limit was crossed" in text and "0 success" in text and "2 bad input" in text
    for option in ("--max-rotation-deg", "--max-position", "--min-registered", "--baseline", "--tolerance"):
        assert option in text


def test_checks_without_the_cli(report):
    """The gate as a library: Check lines, a metric the comparison could not compute, tolerances."""
    found = gate.checks(report, max_rotation_deg=0.05, min_registered=10)
    assert [check.passed for check in found] == [True, True]
    gate.enforce(found)  # nothing crossed: no error
    undefined = dict(report, position_error=None)
    (check,) = gate.checks(undefined, max_position=1.0)
    assert not check.passed and check.line().startswith("position error mean not computed")
    with pytest.raises(RegressionError) as error:
        gate.enforce([check])
    assert error.value.exit_code == 3 and "\n" not in str(error.value)
    # a baseline without a position error gates rotation and registered views only
    assert [c.metric for c in gate.checks(report, baseline=undefined)] == ["rotation error mean",
                                                                          "registered GT cameras"]
    assert gate.parse_tolerance("10%") == pytest.approx(0.1) and gate.parse_tolerance("0.1") == 0.1
    assert gate.parse_tolerance("150%") == pytest.approx(1.5)
    for bad in ("ten", "-5%", "2", "inf"):
        with pytest.raises(InputError):
            gate.parse_tolerance(bad)


def test_readme_ci_lines_run_as_written(tmp_path, capsys, monkeypatch):
    """The README's two CI lines on the Herz-Jesus fixture (data/ = the fixture, the baseline a
    report of the same run: within 10 %); what the run gives is what the README's quick start
    says it prints."""
    import re
    import shlex
    import shutil

    from rotonly_cli.cli import main

    from helpers import REPOSITORY

    readme = (REPOSITORY / "README.md").read_text()
    (block,) = [b for b in re.findall(r"```bash\n(.*?)```", readme, re.S) if "rotonly eval" in b]
    lines = block.strip().splitlines()
    assert len(lines) == 2 and "--baseline" in lines[1] and "--tolerance" in lines[1]
    herz_jesu = DATA_FIXTURES / "herzjesu_p8"
    (tmp_path / "data").mkdir()
    shutil.copyfile(herz_jesu / "database.db", tmp_path / "data" / "database.db")
    (tmp_path / "data" / "gt").symlink_to(herz_jesu)
    monkeypatch.chdir(tmp_path)

    def run(line: str) -> int:
        with pytest.raises(SystemExit) as exit_info:
            main(shlex.split(line)[1:])
        return exit_info.value.code

    assert run(lines[0]) == 0
    summary = json.loads((tmp_path / "OUT" / "reports" / "run.json").read_text())
    printed = capsys.readouterr().out.strip().splitlines()[0]
    (quick_start,) = re.findall(r"prints `([^`]+), …`", readme.replace("\n", " "))
    assert quick_start.startswith(f"{summary['num_registered']}/{summary['num_views']} views registered, "
                                  f"{summary['num_points']} points, {summary['num_active_edges']} active edges")
    assert quick_start.split(", … ")[0] in printed
    assert run(f"rotonly eval --gt data/gt OUT -o {tmp_path / 'baseline'} -q") == 0
    mean = json.loads((tmp_path / "baseline" / "report.json").read_text())["rotation_error_deg"]["mean"]
    assert quick_start.endswith(f"rotation error mean {mean:.4f} deg")
    assert run(lines[1]) == 0, capsys.readouterr().err
    assert "limits held: rotation error mean" in capsys.readouterr().err
