"""The exit-code contract on the bad-input corpus (tests/corpus.py, issue 21): for every case
`rotonly` exits with the case's code (2: bad input or usage), prints exactly one line that
names the file and the field (no traceback, no pycolmap text), writes nothing (no OUT, no
parent folder of OUT, no staging folder, nothing in $TMPDIR) and leaves every input byte
for byte as it was."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path

import pytest

from rotonly_cli.cli import main

from corpus import CASES, HJ4_DB, Case

#: a case that hangs (a named pipe read before it is refused) fails instead of stopping the suite
CASE_TIMEOUT_S = 60


def exit_code(argv: list) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in argv])
    return exit_info.value.code


def snapshot(folder: Path) -> dict[str, object]:
    """Every entry under ``folder``: files by content hash and mode, folders, links, pipes."""
    entries: dict[str, object] = {}
    for directory, folders, files in os.walk(folder):
        for name in folders + files:
            path = Path(directory) / name
            info = path.lstat()
            key = str(path.relative_to(folder))
            if stat.S_ISLNK(info.st_mode):
                entries[key] = ("link", os.readlink(path))
            elif stat.S_ISREG(info.st_mode):
                entries[key] = ("file", hashlib.sha256(path.read_bytes()).hexdigest(), info.st_mode)
            else:
                entries[key] = (stat.S_IFMT(info.st_mode), info.st_mode)
    return entries


@contextmanager
def time_limit(seconds: int):
    def expire(signum, frame):
        raise TimeoutError(f"no answer within {seconds} s (blocked on a read?)")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> dict:
    """What several cases copy: one `rotonly run` of the 4-image fixture (a workspace, and
    its sparse/ as a binary COLMAP model, also written as text)."""
    import pycolmap

    root = tmp_path_factory.mktemp("bases")
    database = root / "input" / "database.db"
    database.parent.mkdir()
    shutil.copyfile(HJ4_DB, database)
    assert exit_code(["-q", "run", database, "-o", root / "run"]) == 0
    (root / "model_txt").mkdir()
    pycolmap.Reconstruction(str(root / "run" / "sparse")).write_text(str(root / "model_txt"))
    bases = {"root": root, "workspace": root / "run", "model": root / "run" / "sparse",
             "model_txt": root / "model_txt"}
    bases["snapshot"] = snapshot(root)
    return bases


@pytest.mark.parametrize("case", CASES, ids=[case.name for case in CASES])
def test_bad_input_one_line_nothing_written_inputs_untouched(case: Case, bases, tmp_path, capsys, monkeypatch):
    root = tmp_path / "case"
    root.mkdir()
    private_tmp = tmp_path / "tmpdir"
    private_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private_tmp))
    argv = case.build(root, bases)
    capsys.readouterr()
    before = snapshot(tmp_path)
    with time_limit(CASE_TIMEOUT_S):
        code = exit_code(["-q", *argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and "Check failed" not in err, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for expected in case.expect:
        assert expected in lines[0], f"{expected!r} not in {lines[0]!r}"
    assert code == case.code, err
    assert snapshot(tmp_path) == before  # nothing written (no OUT, no parents, no $TMPDIR file), inputs intact
    assert snapshot(bases["root"]) == bases["snapshot"]


def test_the_corpus_covers_every_kind_of_the_issue():
    """Issue 21's kinds: special files, JSON depth and number size, non-finite / negative /
    zero intrinsics and keypoints, truncated blobs, every input format, workspaces, OUT."""
    prefixes = {case.name.split("-")[0] for case in CASES}
    assert {"db", "db38", "fifo", "device", "json", "feat", "matches", "gt", "model", "ws", "out", "eval",
            "usage"} <= prefixes
    names = " ".join(case.name for case in CASES)
    for kind in ("deep-nesting", "huge-integer", "focal-nan", "focal-negative", "focal-zero", "width-zero",
                 "principal-point-outside", "keypoint-nan", "keypoints-truncated", "qvec-nan", "camera-size-nan",
                 "state-truncated", "meta-without-views", "parent-is-a-file"):
        assert kind in names, kind
    assert len(CASES) >= 150
