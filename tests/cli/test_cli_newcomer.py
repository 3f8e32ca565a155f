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
