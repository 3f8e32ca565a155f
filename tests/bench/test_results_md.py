"""docs/results.md sections: written by the benchmarks, a rerun replaces only its own section."""

from __future__ import annotations

from pathlib import Path

from rotonly_cli.bench import results_md


def test_record_writes_replaces_and_keeps_the_other_sections(tmp_path: Path):
    path = tmp_path / "results.md"
    assert results_md.record(None, "a", "A", "cmd a", "| x |") is None and not path.exists()
    results_md.record(path, "a", "Table A", "rotonly bench a", "| a | 1 |")
    results_md.record(path, "b", "Table B", "python b.py", "| b | 2 |")
    results_md.record(path, "a", "Table A", "rotonly bench a --more", "| a | 3 |")
    text = path.read_text()
    assert text.startswith(results_md.HEADER)
    assert text.count("<!-- results:a -->") == 1 and text.count("<!-- results:b -->") == 1
    assert "| a | 3 |" in text and "| a | 1 |" not in text and "| b | 2 |" in text
    assert text.index("results:a") < text.index("results:b")  # replaced in place
    assert "`rotonly bench a --more`" in text and "## Table A" in text


def test_section_headings_sit_under_the_title():
    text = results_md.section("k", "Title", "cmd", "## Table 1\n| a |\n# Other\n### Kept")
    assert "### Table 1" in text and "### Other" in text and "### Kept" in text
    assert text.count("\n## ") == 1


def test_strip_title_and_command_line():
    assert results_md.strip_title("# rotonly bench x\n\nsome text\n| t |") == "some text\n| t |"
    assert results_md.command_line("python s.py", ["--root", "a b"]) == "python s.py --root 'a b'"


def test_bench_command_writes_its_section(tmp_path: Path):
    from click.testing import CliRunner

    from rotonly_cli.cli import cli

    md = tmp_path / "results.md"
    result = CliRunner().invoke(cli, ["bench", "twoview", "--quick", "--no-progress", "--methods", "TRRM",
                                      "-o", str(tmp_path / "tv"), "--results-md", str(md)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    text = md.read_text()
    assert "<!-- results:bench-twoview -->" in text and "| standard" in text


def test_command_line_writes_no_machine_folders(tmp_path: Path):
    """docs/results.md's commands as any user types them: paths below the working folder
    relative, other absolute ones as named placeholders (results_md.HEADER says which)."""
    cwd = tmp_path / "repo"
    argv = ["--root", "/srv/data/strecha", "--scene=/srv/data/strecha/fountain-P11", "--openmvg-bin",
            "/opt/openmvg/bin", "-o", "/tmp/bench", "--results-md", str(cwd / "docs" / "results.md"),
            "--cache", "/var/cache/x", "--model", "/home/me/model.json", "--trials", "3", "relative/path"]
    assert results_md.command_line("python s.py", argv, cwd) == (
        "python s.py --root DATA/strecha --scene=DATA/strecha/fountain-P11 --openmvg-bin OPENMVG_BIN -o RESULTS "
        "--results-md docs/results.md --cache CACHE --model DATA/model.json --trials 3 relative/path")
    for placeholder in ("`DATA`", "`OPENMVG_BIN`", "`RESULTS`"):
        assert placeholder in results_md.HEADER


def test_results_md_commands_name_no_machine_folders():
    import re
    import shlex

    from helpers import REPOSITORY

    document = (REPOSITORY / "docs" / "results.md").read_text()
    commands = re.findall(r"^`((?:python|rotonly) [^`]*)`", document, re.M)
    assert len(commands) >= 10
    for command in commands:
        assert not [arg for arg in shlex.split(command) if arg.startswith(("/", "../")) or "=/" in arg], command
    assert "root: DATA/strecha;" in document and "../" not in document  # no folder outside the repository
