"""-v, -q and --version work after the subcommand as they do before it; every command's --help
lists the exit codes and the shell completion; one option name per meaning; the README shows
every option --help shows."""

from __future__ import annotations

import re
import shutil

import click
import pytest

from rotonly_cli import __version__
from rotonly_cli.cli import cli, main

from helpers import DATA_FIXTURES, REPOSITORY

DATABASE = DATA_FIXTURES / "herzjesu_p8" / "database.db"


def _rotonly(capsys, *args) -> tuple[int, str, str]:
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def _comparable(stderr: str, out_dir) -> list[str]:
    """The log lines without time stamps, numbers and the OUT path; the -v report lines (their
    wrapping follows the widths of the timings) are left out."""
    lines = []
    for line in stderr.splitlines():
        if "rotonly_cli.monitor:" in line and " s; " not in line:
            continue
        line = re.sub(r"^\d\d:\d\d:\d\d ", "", line).replace(str(out_dir), "OUT")
        lines.append(re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "N", line))
    return lines


@pytest.fixture
def database(tmp_path):
    db = tmp_path / "database.db"
    shutil.copyfile(DATABASE, db)
    return db


def test_version_anywhere(capsys, tmp_path):
    expected = f"rotonly, version {__version__}\n"
    for args in (["--version"], ["run", "--version"], ["run", DATABASE, "-o", tmp_path / "out", "--version"],
                 ["simulate", "twoview", "--version"], ["eval", "--version"]):
        assert _rotonly(capsys, *args)[:2] == (0, expected), args
    assert not (tmp_path / "out").exists()


def test_quiet_and_verbose_after_the_subcommand(capsys, database, tmp_path):
    code, out, quiet_err = _rotonly(capsys, "run", database, "-o", tmp_path / "a", "-q")
    assert code == 0 and quiet_err == "" and "8/8 views registered" in out
    assert _rotonly(capsys, "-q", "run", database, "-o", tmp_path / "b")[2] == ""

    default = _rotonly(capsys, "run", database, "-o", tmp_path / "c")[2]
    assert "DEBUG" not in default and "GRRM iteration" not in default
    # one short line per stage (a line naming the paths is as long as they are)
    assert all(len(line) <= 120 for line in default.splitlines() if str(tmp_path) not in line), default

    leading = _rotonly(capsys, "-v", "run", database, "-o", tmp_path / "d")[2]
    trailing = _rotonly(capsys, "run", database, "-v", "-o", tmp_path / "d")[2]
    for text in (leading, trailing):
        assert "DEBUG rotonly.grrm: GRRM iteration 1:" in text
        assert re.search(r"DEBUG rotonly_cli.monitor: refine: [\d.]+ s; \d+ of 28 edges active \(filtered: too few "
                         r"inliers \d+\)", text)
        assert "refine report: cost_after=" in text
    assert _comparable(leading, tmp_path / "d") == _comparable(trailing, tmp_path / "d")
    # -q wins over -v, wherever each stands
    assert _rotonly(capsys, "-v", "run", database, "-o", tmp_path / "e", "-q")[2] == ""


def test_help_lists_exit_codes_and_completion(capsys):
    for args in (["--help"], ["run", "--help"], ["bench", "strecha", "--help"], ["refine", "--help"]):
        code, out, _ = _rotonly(capsys, *args)
        assert code == 0
        assert "Exit codes: 0 success; 1 no result possible" in out and "2 bad input or usage" in out
        assert "_ROTONLY_COMPLETE=bash_source rotonly" in out
        assert "-v, --verbose" in out and "-q, --quiet" in out and "--version" in out


def _commands(command: click.Command, path: tuple[str, ...] = ()):
    yield path, command
    if isinstance(command, click.Group):
        context = click.Context(command)
        for name in command.list_commands(context):
            yield from _commands(command.get_command(context, name), (*path, name))


def _options():
    """(command path, option names) of every option of every command."""
    for path, command in _commands(cli):
        for param in command.params:
            if isinstance(param, click.Option):
                yield path, param.opts + param.secondary_opts


def test_one_name_per_option():
    """An option name means one thing: the RANSAC threshold is --ransac-max-error everywhere,
    the matches file -M/--matches."""
    names = {name for _, opts in _options() for name in opts}
    assert "--ransac-threshold" not in names and "--ransac-max-error" in names
    spelled = {}
    for _, opts in _options():
        longs = [o for o in opts if o.startswith("--")]
        shorts = [o for o in opts if not o.startswith("--")]
        for short in shorts:  # a short name always abbreviates the same long one
            assert spelled.setdefault(short, tuple(longs)) == tuple(longs), (short, longs)


def test_readme_shows_every_option():
    readme = (REPOSITORY / "README.md").read_text()
    missing = sorted({(" ".join(path), name) for path, opts in _options() for name in opts
                      if name.startswith("--") and name != "--help"
                      and not re.search(rf"{re.escape(name)}(?![\w-])", readme)})
    assert not missing, missing
