"""A COLMAP database that another process is writing (issue 53, io/colmap/database_check.py):
a rollback-journal database is read under SQLite's locks, so that an uncommitted write is
never read (it used to read as "malformed" through ``immutable=1``); a writer holding its lock
longer than rotonly waits ends the run with exit 1 naming the lock; a hot journal is rolled
back in the private copy; the input is never written."""

from __future__ import annotations

import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from rotonly_cli.cli import main
from rotonly_cli.io.colmap import database_check

from helpers import DATA_FIXTURES

#: holds a transaction on the database argv[1]: BEGIN argv[2], the statements argv[4:] with a
#: 5-page cache (so that they spill into the file, as a large write does), then COMMIT after
#: argv[3] seconds ("never": holds until killed)
WRITER = """if True:
    import sqlite3, sys, time
    connection = sqlite3.connect(sys.argv[1], isolation_level=None)
    connection.execute("PRAGMA cache_size=5")
    connection.execute("BEGIN " + sys.argv[2])
    for statement in sys.argv[4:]:
        connection.execute(statement)
    print("held", flush=True)
    time.sleep(3600 if sys.argv[3] == "never" else float(sys.argv[3]))
    connection.execute("COMMIT")
"""
#: a write that rewrites most pages: every keypoint blob grows, every verified pair goes
SPILLING = ("DELETE FROM two_view_geometries", "UPDATE keypoints SET data = randomblob(length(data) + 1000)")


@pytest.fixture
def database(tmp_path) -> Path:
    """The 4-view fixture as a rollback-journal database (COLMAP 3.x's mode; the fixture is WAL)."""
    path = tmp_path / "input" / "database.db"
    path.parent.mkdir()
    shutil.copyfile(DATA_FIXTURES / "colmap38_herzjesu4" / "database.db", path)
    with sqlite3.connect(path) as connection:
        assert connection.execute("PRAGMA journal_mode=DELETE").fetchone() == ("delete",)
    assert not database_check.is_wal(path)
    return path


def _hold(path: Path, mode: str, hold: str, *statements: str) -> subprocess.Popen:
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path), mode, hold, *statements],
                              stdout=subprocess.PIPE, text=True)
    assert writer.stdout.readline().strip() == "held"
    return writer


def _rotonly(capsys, *args) -> tuple[int, list[str]]:
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    return exit_info.value.code, capsys.readouterr().err.splitlines()


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _pairs_loaded(out: Path) -> int:
    return json.loads((out / "reports" / "load.json").read_text())["num_pairs"]


def test_a_write_holding_its_lock_is_waited_for_then_exit_1_naming_the_lock(capsys, tmp_path, database,
                                                                            monkeypatch):
    monkeypatch.setattr(database_check, "BUSY_TIMEOUT_S", 0.5)
    writer = _hold(database, "IMMEDIATE", "never", *SPILLING)  # spilled: it holds the exclusive lock
    try:
        before = _snapshot(database.parent)  # the file as the writer left it so far, and its journal
        out = tmp_path / "out"
        code, err = _rotonly(capsys, "-q", "run", database, "-o", out)
        assert code == 1
        assert err == [f"error: {database}: database is locked by another process (waited 0.5 s for its write to "
                       "end); run again when it is done"]
        assert _snapshot(database.parent) == before  # nothing written to or beside the input
        assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["input"]
    finally:
        writer.kill()
        writer.wait()


def test_a_write_kept_in_the_writers_memory_is_not_read(capsys, tmp_path, database):
    original = database.read_bytes()
    # a small write stays in the writer's cache: it holds the RESERVED lock only, readers go on
    writer = _hold(database, "IMMEDIATE", "never", "PRAGMA cache_size=-2000", "DELETE FROM two_view_geometries "
                   "WHERE rowid IN (SELECT rowid FROM two_view_geometries LIMIT 1)")
    try:
        assert (database.parent / "database.db-journal").is_file()
        code, err = _rotonly(capsys, "-q", "run", database, "-o", tmp_path / "out")
        assert code == 0, err
        assert _pairs_loaded(tmp_path / "out") == 6  # not the 5 of the uncommitted write
        assert database.read_bytes() == original
    finally:
        writer.kill()
        writer.wait()


def test_a_write_committed_while_the_run_waits_is_read_whole(capsys, tmp_path, database):
    writer = _hold(database, "EXCLUSIVE", "1.5", "DELETE FROM two_view_geometries WHERE rowid IN "
                   "(SELECT rowid FROM two_view_geometries LIMIT 1)", "DELETE FROM matches")
    try:
        code, err = _rotonly(capsys, "-q", "run", database, "-o", tmp_path / "out")  # waits up to 10 s
        assert code == 0, err
        assert _pairs_loaded(tmp_path / "out") == 5  # the committed state
    finally:
        writer.wait(timeout=60)


def test_a_hot_journal_is_rolled_back_in_the_private_copy_not_in_the_input(capsys, tmp_path, database):
    writer = _hold(database, "IMMEDIATE", "never", *SPILLING)
    writer.kill()  # mid-transaction: the file holds half the write, the journal the pages it replaced
    writer.wait()
    assert (database.parent / "database.db-journal").is_file()
    before = _snapshot(database.parent)
    code, err = _rotonly(capsys, "-q", "run", database, "-o", tmp_path / "out")
    assert code == 0, err
    assert _pairs_loaded(tmp_path / "out") == 6  # as before the write
    assert _snapshot(database.parent) == before  # the input and its journal untouched


def test_a_wal_database_is_still_read_without_a_file_beside_it(capsys, tmp_path):
    folder = tmp_path / "input"
    folder.mkdir()
    shutil.copyfile(DATA_FIXTURES / "colmap38_herzjesu4" / "database.db", folder / "database.db")
    assert database_check.is_wal(folder / "database.db")
    code, err = _rotonly(capsys, "-q", "run", folder / "database.db", "-o", tmp_path / "out")
    assert code == 0, err
    assert [p.name for p in folder.iterdir()] == ["database.db"]
