"""Faults around `rotonly run` (issue 21), each run as a process: Ctrl-C and kill -9 in the
middle of a run, two runs into one OUT at once, a full disk under OUT or $TMPDIR, a
read-only destination, an input whose file name is not UTF-8. At every moment OUT is absent,
the previous workspace or the new one, complete; whatever a killed run left is gone after
the next run; every error is one line. (scripts/faults/interrupt_runs.py does the same at
many more moments.)"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from rotonly_cli.io.workspace import load_state

from helpers import DATA_FIXTURES

DB = DATA_FIXTURES / "colmap38_herzjesu4" / "database.db"
RUN = "from rotonly_cli.cli import console_main; console_main()"
WORKSPACE_FILES = ("sfm_data.json", "view_graph.json", "run.log", "state.npz", "sparse/cameras.bin",
                   "sparse/images.bin", "sparse/points3D.bin", "reports/run.json")


def start(argv: list, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", RUN, *map(str, argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})


def finish(process: subprocess.Popen) -> tuple[int, str]:
    _, err = process.communicate(timeout=600)
    return process.returncode, err


def assert_complete_workspace(out: Path) -> None:
    missing = [name for name in WORKSPACE_FILES if not (out / name).is_file()]
    assert not missing, missing
    assert load_state(out).stages[-1] == "triangulate"


def leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> Path:
    """A finished workspace (what OUT holds before the faulty runs)."""
    root = tmp_path_factory.mktemp("previous")
    code, err = finish(start(["-q", "run", DB, "-o", root / "out"]))
    assert code == 0, err
    return root / "out"


def _fresh_out(tmp_path: Path, previous: Path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(previous, out)
    (out / "run.log").write_text("the previous workspace\n")
    return out


def _wait_for_staging(out: Path, process: subprocess.Popen, delay: float) -> None:
    """Until the run has made its staging folder (and ``delay`` seconds more)."""
    deadline = time.monotonic() + 60
    while not leftovers(out) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(delay)


@pytest.mark.parametrize("delay", [0.0, 0.3])
def test_ctrl_c_exits_130_in_one_line_and_keeps_the_previous_workspace(tmp_path, previous, delay):
    out = _fresh_out(tmp_path, previous)
    process = start(["run", DB, "-o", out])
    _wait_for_staging(out, process, delay)
    process.send_signal(signal.SIGINT)
    code, err = finish(process)
    if code == 0:  # the run was already done
        assert_complete_workspace(out)
        return
    assert code == 130, err
    assert err.strip().splitlines()[-1] == "error: interrupted"
    assert "Traceback" not in err
    assert (out / "run.log").read_text() == "the previous workspace\n"
    assert leftovers(out) == []


@pytest.mark.parametrize("delay", [0.0, 0.2, 0.5])
def test_kill_9_leaves_the_previous_workspace_and_the_next_run_cleans_up(tmp_path, previous, delay):
    out = _fresh_out(tmp_path, previous)
    process = start(["run", DB, "-o", out])
    _wait_for_staging(out, process, delay)
    process.kill()
    finish(process)
    assert_complete_workspace(out)  # old or new, whole
    code, err = finish(start(["-q", "run", DB, "-o", out]))
    assert code == 0, err
    assert_complete_workspace(out)
    assert leftovers(out) == []


def test_two_runs_into_one_out_at_once_leave_one_complete_workspace(tmp_path):
    out = tmp_path / "out"
    runs = [start(["-q", "run", DB, "-o", out]) for _ in range(2)]
    results = [finish(process) for process in runs]
    assert [code for code, _ in results] == [0, 0], results
    assert_complete_workspace(out)
    assert leftovers(out) == []


def test_an_input_file_name_that_is_not_utf8(tmp_path):
    name = os.fsdecode(b"data\xff.db")
    shutil.copyfile(DB, tmp_path / name)
    code, err = finish(start(["run", tmp_path / name, "-o", tmp_path / "out"]))
    assert code == 0 and "Traceback" not in err and "Logging error" not in err, err
    (tmp_path / name).write_bytes(b"broken")
    code, err = finish(start(["run", tmp_path / name, "-o", tmp_path / "out2"]))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "not an SQLite file" in err, err


# ============================================================================ file systems

def _can_mount() -> bool:
    if not sys.platform.startswith("linux") or os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    probe = Path(os.environ.get("TMPDIR", "/tmp")) / f"rotonly-mount-probe-{os.getpid()}"
    probe.mkdir(exist_ok=True)
    try:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(probe)],
                            capture_output=True).returncode == 0
        if ok:
            subprocess.run(["umount", str(probe)], check=True)
        return ok
    finally:
        probe.rmdir()


needs_mount = pytest.mark.skipif(not _can_mount(), reason="needs root and tmpfs mounts")


@contextmanager
def tmpfs(folder: Path, options: str):
    folder.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], check=True)
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


#: a rollback-journal database (DB is a WAL one): its private copy is SQLite's backup, whose
#: full disk is an SQLite error, not an OSError
JOURNAL_DB = DATA_FIXTURES / "herzjesu_p8" / "database.db"


@needs_mount
@pytest.mark.parametrize("size, database", [("512k", DB), ("2m", DB), ("512k", JOURNAL_DB)])
def test_full_disk_under_out_is_one_line_exit_1_and_leaves_nothing(tmp_path, size, database):
    with tmpfs(tmp_path / "small", f"size={size}") as small:
        code, err = finish(start(["run", database, "-o", small / "deep" / "out"]))
        assert code == 1, err
        lines = err.strip().splitlines()
        assert lines[-1].startswith("error: ") and "No space left on device" in lines[-1], err
        assert "Traceback" not in err and not any(line.startswith("error") for line in lines[:-1])
        assert list(small.iterdir()) == []


@needs_mount
def test_full_tmpdir_is_not_used(tmp_path):
    with tmpfs(tmp_path / "tmp", "size=64k") as tmp:
        (tmp / "filler").write_bytes(b"\0" * (64 * 1024))  # the whole of it
        code, err = finish(start(["-q", "run", DB, "-o", tmp_path / "out"], env={"TMPDIR": str(tmp)}))
        assert code == 0, err
        assert_complete_workspace(tmp_path / "out")
        assert [p.name for p in tmp.iterdir()] == ["filler"]


@needs_mount
def test_read_only_destination_is_one_line_exit_2(tmp_path):
    with tmpfs(tmp_path / "ro", "ro,size=64k") as read_only:
        code, err = finish(start(["run", DB, "-o", read_only / "out"]))
        assert code == 2, err
        assert err.strip().splitlines() == [f"error: {read_only / 'out'}: -o: cannot write: Read-only file system"]


def test_ctrl_c_that_a_library_wrapped_is_still_an_interrupt(tmp_path, monkeypatch, capsys):
    """pycolmap turns a KeyboardInterrupt during its import into RuntimeError (from
    ImportError): still exit 130 and one line."""
    from rotonly_cli import pipeline
    from rotonly_cli.cli import main

    def interrupted_import(*args, **kwargs):
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as exc:
                raise ImportError("initialization failed") from exc
        except ImportError as exc:
            raise RuntimeError("Cannot import the C++ backend pycolmap._core.") from exc

    monkeypatch.setattr(pipeline, "check_input", interrupted_import)
    with pytest.raises(SystemExit) as exit_info:
        main(["run", str(DB), "-o", str(tmp_path / "out")])
    assert exit_info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == ["error: interrupted"]
    assert list(tmp_path.iterdir()) == []


@needs_mount
def test_out_that_is_a_mount_point_is_refused_before_the_run(tmp_path):
    with tmpfs(tmp_path / "out", "size=1m") as out:
        code, err = finish(start(["run", DB, "-o", out]))
        assert code == 2, err
        assert err.strip().splitlines() == [f"error: {out}: -o: is a mount point: it cannot be replaced in one step "
                                            "(give a folder inside it)"]
        assert list(out.iterdir()) == [] and leftovers(out) == []


# ============================================================================ Ctrl-C around the commit (issue 53)

#: the console script with SIGINT sent to itself at one moment around the commit of OUT
INTERRUPTED_RUN = """if True:
    import os, signal, sys
    from rotonly_cli import pipeline
    from rotonly_cli.cli import run
    from rotonly_cli.io import atomic

    def around(owner, name, before):
        original = getattr(owner, name)

        def patched(*args, **kwargs):
            # Staging._exchange: OUT's only (the models' folders inside the workspace are staged too)
            now = not isinstance(args[0], atomic.Staging) or args[0].target.name == "out"
            if before and now:
                os.kill(os.getpid(), signal.SIGINT)
            result = original(*args, **kwargs)
            if not before and now:
                os.kill(os.getpid(), signal.SIGINT)
            return result

        setattr(owner, name, patched)

    where = sys.argv.pop(1)
    {"before the workspace is finished": lambda: around(pipeline, "_finish", before=False),
     "as the commit starts": lambda: around(atomic.Staging, "_exchange", before=True),
     "right after the exchange": lambda: around(atomic.Staging, "_exchange", before=False),
     "while the summary is printed": lambda: around(run, "echo_summary", before=True)}[where]()
    from rotonly_cli.cli import console_main
    sys.argv[0] = "rotonly"
    console_main()
"""


@pytest.mark.parametrize("moment, new", [("before the workspace is finished", False), ("as the commit starts", True),
                                         ("right after the exchange", True), ("while the summary is printed", True)])
def test_ctrl_c_around_the_commit_exits_130_with_out_as_before_or_0_with_out_new(tmp_path, previous, moment, new):
    out = _fresh_out(tmp_path, previous)
    completed = subprocess.run([sys.executable, "-c", INTERRUPTED_RUN, moment, "run", str(DB), "-o", str(out)],
                               capture_output=True, text=True, timeout=300)
    assert "Traceback" not in completed.stderr and "Exception ignored" not in completed.stderr, completed.stderr
    if new:  # the commit had begun: the command succeeded, and says so
        assert completed.returncode == 0, completed.stderr
        assert "error" not in completed.stderr
        assert completed.stdout.startswith(f"{out}: 4/4 views registered"), completed.stdout
        assert (out / "run.log").read_text() != "the previous workspace\n"
        assert_complete_workspace(out)
    else:
        assert completed.returncode == 130, completed.stderr
        assert completed.stderr.strip().splitlines()[-1] == "error: interrupted"
        assert (out / "run.log").read_text() == "the previous workspace\n"
    assert leftovers(out) == []


# ============================================================================ kill -9 with workers alive (issue 53)

@pytest.fixture(scope="module")
def fault_scripts():
    """scripts/faults/processes.py and kill_workers.py (process groups, bounded waits)."""
    folder = str(Path(__file__).resolve().parents[1] / "scripts" / "faults")
    sys.path.insert(0, folder)
    try:
        import kill_workers
        import processes
    finally:
        sys.path.remove(folder)
    return processes, kill_workers


@pytest.mark.parametrize("nth", [1, 3])  # the first worker (identification), the third (GRRM's helper)
def test_kill_9_of_the_main_process_leaves_no_worker_alive_and_the_next_run_cleans_up(tmp_path, previous,
                                                                                       fault_scripts, nth):
    processes, kill_workers = fault_scripts
    out = _fresh_out(tmp_path, previous)
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    # 500 matches per part: the 4-view fixture forks its workers as a large input does
    run = processes.start(["-q", "run", DB, "-o", out], tmpdir, min_matches_per_job=500)
    alive, _ = kill_workers.kill_when_a_worker_lived(run, nth, 0.0, 120)
    killed = processes.finish(run, 30)
    assert alive, "no worker was alive at the kill"
    assert killed.orphans == [], f"processes of the killed run alive {processes.ORPHAN_GRACE_S} s later"
    assert_complete_workspace(out)  # old or new, whole
    after = processes.finish(processes.start(["-q", "run", DB, "-o", out], tmpdir, min_matches_per_job=500), 300)
    assert after.code == 0 and not after.orphans, after.stderr
    assert leftovers(out) == [] and list(tmpdir.iterdir()) == []
