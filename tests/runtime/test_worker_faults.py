"""Forked workers under faults (issue 53, runtime/parallel.py): they die with their parent,
hold none of its pipe ends, a Ctrl-C during a fork is raised in the parent instead of being
lost in an at-fork hook, out of memory in a worker stays a MemoryError, and a fork the system
refuses costs time, not the run."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from rotonly_cli.runtime import parallel

from helpers import REPOSITORY

pytestmark = pytest.mark.skipif(not parallel.fork_safe(), reason="needs fork (Linux, no other thread)")


def _python(code: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], cwd=REPOSITORY, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPOSITORY)}, **kwargs)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie that nobody reaped yet is dead)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except OSError:
        return False


def test_workers_die_with_their_parent_killed_by_sigkill():
    # a helper peer blocked reading its pipe and a forked call busy for a minute: before issue 53
    # the peer never saw EOF (it held the parent's end itself) and nothing tied either to the parent
    code = """if True:
        import time
        from rotonly_cli.runtime import parallel
        peer = parallel.ForkedPeer(lambda message: message)
        call = parallel.ForkedCall(lambda: time.sleep(60))
        print(peer._process.pid, call._process.pid, flush=True)
        time.sleep(60)
    """
    process = _python(code, stdout=subprocess.PIPE)
    children = [int(pid) for pid in process.stdout.readline().split()]
    assert len(children) == 2 and all(_alive(pid) for pid in children)
    process.kill()
    process.wait(timeout=10)
    deadline = time.monotonic() + 3.0
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.02)
    survivors = [pid for pid in children if _alive(pid)]
    for pid in survivors:  # do not leave them to the rest of the test session
        os.kill(pid, signal.SIGKILL)
    assert survivors == []


def test_a_child_whose_parent_died_before_it_asked_to_die_with_it_exits():
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        try:
            parallel._enter_child(parent=os.getppid() + 1_000_000)  # not its parent: as if reparented
        finally:
            os._exit(0)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 1


def test_workers_hold_no_copy_of_the_parents_pipe_ends():
    with parallel.ForkedPeer(lambda message: message) as peer:
        end = os.fstat(peer._conn.fileno())

        def copies(_):
            """Open descriptors of this child that are the peer's parent end."""
            found = 0
            for name in os.listdir("/proc/self/fd"):
                try:
                    info = os.fstat(int(name))
                except OSError:
                    continue
                found += (info.st_dev, info.st_ino) == (end.st_dev, end.st_ino)
            return found

        assert parallel.fork_map(copies, [0, 1, 2]) == [1, 0, 0]  # the parent itself holds it, once
        peer.submit("ping")
        assert peer.collect() == "ping"


def test_ctrl_c_while_a_worker_is_forked_is_raised_in_the_parent():
    # SIGINT arrives inside os.fork's at-fork hooks (ours runs first, then logging's): raised there,
    # the KeyboardInterrupt was printed as "Exception ignored" and the run went on
    # Python installs its KeyboardInterrupt handler only where SIGINT is not ignored, and a
    # background job of a non-interactive shell (`pytest &`) starts with it ignored: set it here
    code = """if True:
        import logging, os, signal
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from rotonly_cli.runtime import parallel
        armed = []
        os.register_at_fork(before=lambda: armed and os.kill(os.getpid(), signal.SIGINT))
        armed.append(True)
        try:
            parallel.fork_map(lambda x: x, [1, 2])
            print("not interrupted")
        except KeyboardInterrupt:
            print("interrupted")
    """
    completed = subprocess.run([sys.executable, "-c", code], cwd=REPOSITORY, capture_output=True, text=True,
                               timeout=60, env={**os.environ, "PYTHONPATH": str(REPOSITORY)})
    assert completed.stdout.strip() == "interrupted", completed
    assert "Exception ignored" not in completed.stderr, completed.stderr


def test_a_memory_error_in_a_worker_is_a_memory_error_here():
    def allocate(x):
        if x:
            np.empty(1 << 46, dtype=np.uint8)  # numpy's _ArrayMemoryError
        return x

    with pytest.raises(MemoryError, match="Unable to allocate 64.0 TiB"):
        parallel.fork_map(allocate, [0, 1])


class _Unpicklable:
    def __reduce__(self):
        raise MemoryError("no memory left to pickle the result")


def test_a_result_that_runs_out_of_memory_being_sent_is_a_memory_error_here():
    # it used to come back as RuntimeError("worker result could not be sent back"): a traceback
    with pytest.raises(MemoryError, match="no memory left to pickle the result"):
        parallel.fork_map(lambda x: _Unpicklable() if x else x, [0, 1])


def test_a_fork_the_system_refuses_is_done_in_this_process(monkeypatch, caplog):
    import multiprocessing.context

    def refuse(self):
        raise OSError(errno.EAGAIN, os.strerror(errno.EAGAIN))

    monkeypatch.setattr(multiprocessing.context.ForkProcess, "start", refuse)
    assert parallel.fork_map(lambda x: (x, os.getpid()), [1, 2, 3]) == [(x, os.getpid()) for x in (1, 2, 3)]
    with parallel.ForkedPeer(lambda message: (message, os.getpid())) as peer:
        assert not peer.alive
        peer.submit("ping")
        assert peer.collect() == ("ping", os.getpid())
    assert parallel.ForkedCall(lambda: os.getpid()).result() == os.getpid()
    warnings = [r.getMessage() for r in caplog.records if "could be started" in r.getMessage()]
    assert len(warnings) == 4 and all("Resource temporarily unavailable" in w for w in warnings), warnings
