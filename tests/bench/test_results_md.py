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
