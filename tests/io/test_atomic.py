"""io.atomic.Staging: a folder that replaces its target whole, whose leftovers after a kill the
next staging of the same target removes, and which never touches what is not its own."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.io.atomic import STAGING_MARKER, Staging, check_replaceable, remove_stale, staging_dir


def _workspace(folder: Path, content: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "run.log").write_text(content)
    return folder


def _siblings(target: Path) -> list[str]:
    return sorted(p.name for p in target.parent.iterdir() if p.name != target.name)


def _killed_staging(target: Path, *, first_rename: bool = False) -> Path:
    """A staging folder of ``target`` left by a process that died (os._exit): with
    ``first_rename`` it died between the two renames of the fallback (old target inside)."""
    code = textwrap.dedent(f"""
        import os
        from pathlib import Path
        from rotonly_cli.io.atomic import Staging
        staging = Staging({str(target)!r})
        (staging.new / "run.log").write_text("new")
        if {first_rename!r}:
            os.rename(staging.target, staging.root / "old")
        print(staging.root)
        os._exit(0)
    """)
    root = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    return Path(root)


def test_commit_puts_a_new_target_in_place_and_leaves_nothing_beside_it(tmp_path):
    target = tmp_path / "out"
    staging = Staging(target)
    _workspace(staging.new, "new")
    assert (staging.root / STAGING_MARKER).is_file() and staging.root.name.startswith(".out.")
    staging.commit()
    assert (target / "run.log").read_text() == "new"
    assert _siblings(target) == []


def test_commit_exchanges_an_existing_target(tmp_path):
    target = _workspace(tmp_path / "out", "old")
    with staging_dir(target) as new:
        (new / "run.log").write_text("new")
        assert (target / "run.log").read_text() == "old"  # the old one stays until the end
    assert (target / "run.log").read_text() == "new"
    assert _siblings(target) == []


def test_a_failure_leaves_the_target_and_removes_the_parents_it_made(tmp_path):
    target = tmp_path / "a" / "b" / "out"
    with pytest.raises(RuntimeError), staging_dir(target) as new:
        (new / "run.log").write_text("new")
        raise RuntimeError("stage failed")
    assert list(tmp_path.iterdir()) == []
    existing = _workspace(tmp_path / "out", "old")
    with pytest.raises(RuntimeError), staging_dir(existing):
        raise RuntimeError("stage failed")
    assert (existing / "run.log").read_text() == "old" and _siblings(existing) == []


def test_the_next_staging_removes_what_a_killed_run_left(tmp_path):
    target = _workspace(tmp_path / "out", "old")
    first = _killed_staging(target)
    second = _killed_staging(target)  # its staging removed the first one's leftover
    assert not first.exists() and second.is_dir()
    with staging_dir(target) as new:
        (new / "run.log").write_text("new")
        assert not second.exists()
    assert (target / "run.log").read_text() == "new" and _siblings(target) == []


def test_a_live_staging_and_folders_that_are_not_rotonlys_are_kept(tmp_path):
    target = tmp_path / "out"
    live = Staging(target)  # locked by this process
    foreign = tmp_path / ".out.mine.tmp"  # same name pattern, no marker
    foreign.mkdir()
    other = _killed_staging(tmp_path / "out.x")  # a dead staging of another target: ".out.x.*.tmp"
    assert remove_stale(target) == []
    assert live.root.is_dir() and foreign.is_dir() and other.is_dir()
    assert remove_stale(tmp_path / "out.x") == [other]
    live.discard()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.mine.tmp"]


def test_a_run_killed_before_its_marker_existed_is_cleaned_up_and_a_live_one_is_not(tmp_path):
    """A kill between mkdtemp and the marker's rename leaves an empty folder or one holding the
    marker's temporary file: removed unless that file is locked (a live run making its folder)."""
    import fcntl

    target = tmp_path / "out"
    empty = tmp_path / ".out.abcd1234.tmp"
    empty.mkdir()
    half = tmp_path / ".out.efgh5678.tmp"
    half.mkdir()
    (half / ".lock.xyz").write_text("")
    live = tmp_path / ".out.ijkl9012.tmp"
    live.mkdir()
    handle = os.open(live / ".lock.abc", os.O_CREAT | os.O_RDWR)
    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    user = tmp_path / ".out.mnop3456.tmp"  # same pattern, but holds something else: never touched
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    try:
        assert sorted(remove_stale(target)) == sorted([empty, half])
        assert live.is_dir() and (user / "notes.txt").read_text() == "mine"
    finally:
        os.close(handle)
    assert remove_stale(target) == [live]


def test_concurrent_stagings_each_put_a_complete_target_in_place(tmp_path):
    target = tmp_path / "out"
    first, second = Staging(target), Staging(target)
    _workspace(first.new, "first")
    _workspace(second.new, "second")
    first.commit()
    second.commit()
    assert (target / "run.log").read_text() == "second"
    assert _siblings(target) == []


def test_without_renameat2_two_renames_and_a_kill_between_them_is_repaired(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_renameat2_function", None)
    target = _workspace(tmp_path / "out", "old")
    with staging_dir(target) as new:
        (new / "run.log").write_text("new")
    assert (target / "run.log").read_text() == "new" and _siblings(target) == []
    left = _killed_staging(target, first_rename=True)
    assert not target.exists() and (left / "old" / "run.log").read_text() == "new"
    remove_stale(target)  # the next run first puts the old workspace back
    assert (target / "run.log").read_text() == "new" and _siblings(target) == []


def test_commit_checks_the_target_again_before_replacing_it(tmp_path):
    target = tmp_path / "out"
    staging = Staging(target)
    target.mkdir()
    (target / "thesis.tex").write_text("written meanwhile")
    with pytest.raises(InputError, match="not a rotonly workspace"):
        staging.commit(lambda path: check_replaceable(path, {"run.log"}, "a rotonly workspace"))
    staging.discard()
    assert (target / "thesis.tex").read_text() == "written meanwhile" and _siblings(target) == []


def test_unusable_destinations_are_input_errors(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        Staging(tmp_path / "file" / "sub" / "out")
    os.symlink(tmp_path / "nowhere", tmp_path / "link")
    with pytest.raises(InputError, match="broken symbolic link"):
        Staging(tmp_path / "link" / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "link"]


def test_replaceable_allows_the_temporary_files_of_a_killed_stage_command(tmp_path):
    (tmp_path / "state.npz").write_bytes(b"")
    (tmp_path / ".state.npz.ab12cd.npz").write_bytes(b"")
    check_replaceable(tmp_path, {"state.npz"}, "a rotonly workspace")
    (tmp_path / ".thesis.tex.swp").write_bytes(b"")
    with pytest.raises(InputError, match="thesis"):
        check_replaceable(tmp_path, {"state.npz"}, "a rotonly workspace")


# ============================================================================ faults of issue 53

def _dead_run_with_a_live_child(target: Path, keep_lock: bool) -> tuple[Path, int]:
    """A run that made a staging folder of ``target``, forked a child and died (os._exit), the
    child alive: (the folder, the child's pid). ``keep_lock``: the child holds a copy of the
    lock's descriptor that no at-fork hook knows (made by os.dup before the fork), as a child
    forked by other code, or by rotonly before issue 53, did."""
    code = textwrap.dedent(f"""
        import os, time
        from rotonly_cli.io.atomic import Staging
        staging = Staging({str(target)!r})
        kept = os.dup(staging.lock) if {keep_lock!r} else None
        child = os.fork()
        if child == 0:
            for stream in (1, 2):  # the test reads the parent's output to its end
                os.dup2(os.open(os.devnull, os.O_RDWR), stream)
            time.sleep(60)
            os._exit(0)
        print(staging.root, child, flush=True)
        os._exit(0)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    return Path(out[0]), int(out[1])


@pytest.mark.parametrize("keep_lock", [False, True])
def test_a_dead_runs_folder_is_removed_although_its_child_lives(tmp_path, keep_lock):
    # the child closes its copy of the lock at the fork; one that kept it (an orphan of a killed
    # run) holds the lock, and the marker's run being dead (pid and start time) decides
    target = _workspace(tmp_path / "out", "old")
    left, child = _dead_run_with_a_live_child(target, keep_lock)
    try:
        assert left.is_dir()
        assert remove_stale(target) == [left]
        assert _siblings(target) == []
    finally:
        os.kill(child, 9)


def test_a_live_runs_folder_is_kept_whoever_else_holds_its_lock(tmp_path):
    target = tmp_path / "out"
    live = Staging(target)
    kept = os.dup(live.lock)
    try:
        assert remove_stale(target) == [] and live.root.is_dir()
    finally:
        os.close(kept)
        live.discard()


def _interrupt_once(monkeypatch, owner, name: str, before: bool) -> None:
    """``owner.name`` sends this process SIGINT once, before or after doing its work; Python's
    own handler (KeyboardInterrupt) is the one in force, whatever an earlier test left."""
    import signal

    signal.signal(signal.SIGINT, signal.default_int_handler)  # conftest restores the one found
    original = getattr(owner, name)
    sent = []

    def interrupted(*args, **kwargs):
        if before and not sent:
            sent.append(signal.raise_signal(signal.SIGINT))
        result = original(*args, **kwargs)
        if not before and not sent:
            sent.append(signal.raise_signal(signal.SIGINT))
        return result

    monkeypatch.setattr(owner, name, interrupted)


@pytest.mark.parametrize("before", [True, False])
def test_ctrl_c_during_the_commit_is_raised_once_the_target_is_new_and_the_folder_gone(tmp_path, monkeypatch,
                                                                                        before):
    target = _workspace(tmp_path / "out", "old")
    staging = Staging(target)
    _workspace(staging.new, "new")
    _interrupt_once(monkeypatch, atomic, "_renameat2", before)
    told = []
    with pytest.raises(KeyboardInterrupt):
        staging.commit(committed=lambda: told.append((target / "run.log").read_text()))
    assert told == ["new"]  # the caller learnt of the new target before the Ctrl-C was raised
    assert (target / "run.log").read_text() == "new" and _siblings(target) == []


def test_ctrl_c_while_the_staging_folder_is_made_leaves_no_folder(tmp_path, monkeypatch):
    target = _workspace(tmp_path / "out", "old")
    _interrupt_once(monkeypatch, atomic.tempfile, "mkdtemp", before=False)  # the folder exists, unnamed
    with pytest.raises(KeyboardInterrupt):
        Staging(target)
    assert _siblings(target) == []
