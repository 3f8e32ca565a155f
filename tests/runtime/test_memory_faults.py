"""Out of memory anywhere in a run is one line (issue 53 point 2): exit 1, exactly one `error:`
line naming the stage (or the stage before), the allocation and the predicted need, no
traceback, OUT byte-identical; also in a forked worker, in a writer, while logging, outside
every stage, and under a real address-space limit (setrlimit in a child process)."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli import chain, pipeline
from rotonly_cli.cli import main
from rotonly_cli.runtime import parallel

from helpers import DATA_FIXTURES, REPOSITORY, folder_bytes

DATABASE = DATA_FIXTURES / "colmap38_herzjesu4" / "database.db"
ALLOCATION = r"Unable to allocate 64\.0 TiB for an array with shape \(70368744177664,\) and data type uint8"


def _allocate(*_):
    np.empty(1 << 46, dtype=np.uint8)  # 64 TiB: numpy's _ArrayMemoryError


@pytest.fixture
def previous_out(tmp_path) -> Path:
    out = tmp_path / "out"
    (out / "reports").mkdir(parents=True)
    (out / "run.log").write_bytes(b"sentinel run.log\n")
    return out


def _one_line_and_out_unchanged(capsys, out: Path) -> str:
    before = folder_bytes(out)
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", "run", str(DATABASE), "-o", str(out)])
    err = capsys.readouterr().err.splitlines()
    assert exit_info.value.code == 1, err
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert folder_bytes(out) == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]  # no staging folder left
    return err[0]


@pytest.mark.skipif(not parallel.fork_safe(), reason="needs fork")
def test_in_a_forked_worker(capsys, previous_out, monkeypatch):
    monkeypatch.setitem(chain.STAGE_FUNCTIONS, "refine", lambda run: parallel.fork_map(
        lambda x: _allocate() if x else x, [0, 1]))
    line = _one_line_and_out_unchanged(capsys, previous_out)
    assert re.fullmatch(rf"error: refine ran out of memory \({ALLOCATION}\); it needs about 0\.16 GB \(.*\)",
                        line), line


def test_in_a_writer(capsys, previous_out, monkeypatch):
    monkeypatch.setattr(pipeline, "write_view_graph_json", _allocate)
    line = _one_line_and_out_unchanged(capsys, previous_out)
    assert re.fullmatch(rf"error: export ran out of memory \({ALLOCATION}\); it needs about 0\.\d+ GB \(.*\)",
                        line), line


def test_while_logging(capsys, previous_out, monkeypatch):
    class Unprintable:
        def __str__(self):
            raise MemoryError("no memory to format the record")

    # before issue 53 logging printed a "--- Logging error ---" traceback and the run went on
    monkeypatch.setitem(chain.STAGE_FUNCTIONS, "average",
                        lambda run: logging.getLogger("rotonly_cli.chain").warning("%s", Unprintable()))
    line = _one_line_and_out_unchanged(capsys, previous_out)
    assert re.fullmatch(r"error: average ran out of memory \(no memory to format the record\); it needs about .*",
                        line), line


def test_between_stages(capsys, previous_out, monkeypatch):
    import rotonly_cli.components

    monkeypatch.setattr(rotonly_cli.components, "reconstruct", _allocate)  # the other components: no guard
    line = _one_line_and_out_unchanged(capsys, previous_out)
    assert re.fullmatch(rf"error: out of memory after the triangulate stage \({ALLOCATION}\); it needs about .*",
                        line), line


def test_a_thread_that_cannot_start(capsys, previous_out, monkeypatch):
    import threading

    def no_stack(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", no_stack)
    line = _one_line_and_out_unchanged(capsys, previous_out)
    assert re.fullmatch(r"error: load ran out of memory \(can't start new thread\); it needs about 0\.16 GB .*", line)


#: the console script under an address-space limit (what `prlimit --as` sets) of argv[1] MiB above
#: what it has mapped once imported; the guard sees no limit (available_bytes None), as when its
#: prediction is short, so the run meets the limit in its allocations
CAPPED = """if True:
    import resource, sys
    from rotonly_cli.runtime import startup
    startup.rotonly_process_settings()
    import numpy, scipy.sparse.linalg, pycolmap, rotonly_cli.pipeline
    from rotonly_cli import chain
    from rotonly_cli.runtime import memory, parallel
    memory.available_bytes = lambda: None
    if sys.argv[2] == "forked":  # a worker of the refine stage allocates 1 GiB
        chain.STAGE_FUNCTIONS["refine"] = lambda run: parallel.fork_map(
            lambda x: numpy.ones(1 << 27) if x else x, [0, 1])
    cap = memory._status_kb("VmSize") * 1024 + int(sys.argv[1]) * 2 ** 20
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    from rotonly_cli.cli import main
    main(sys.argv[3:])
"""


@pytest.mark.parametrize("room_mb, where, expected", [
    (60, "", r"error: the run needs about 0\.\d+ GB of address space to start \(the BLAS buffers and threads\), "
             r"above the limit of 0\.\d+ GB \(address-space limit\)"),
    (400, "forked", r"error: refine ran out of memory \(Unable to allocate 1\.00 GiB for an array with shape "
                    r"\(134217728,\) and data type float64\); it needs about 0\.16 GB \(.*\)")])
def test_under_an_address_space_limit(tmp_path, previous_out, room_mb, where, expected):
    before = folder_bytes(previous_out)
    completed = subprocess.run([sys.executable, "-c", CAPPED, str(room_mb), where or "-", "-q", "run", str(DATABASE),
                                "-o", str(previous_out)], capture_output=True, text=True, timeout=120,
                               cwd=REPOSITORY, env={**os.environ, "PYTHONPATH": str(REPOSITORY)})
    lines = completed.stderr.splitlines()
    assert completed.returncode == 1, completed.stderr[-3000:]
    assert len(lines) == 1 and re.fullmatch(expected, lines[0]), lines
    assert folder_bytes(previous_out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
