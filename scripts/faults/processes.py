"""Runs of `rotonly` as process groups, for the fault scripts: every process a run forks shares
its group, so the processes of a run that outlive it (orphans) can be found, reported and
ended, and no wait here is unbounded (issue 53): a run's output goes to files, not pipes, which
an orphan holding them would keep open forever.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]
#: the console script (rotonly_cli/console.py), run from this checkout; MIN_MATCHES_PER_JOB (argv[1]) may
#: be lowered so that a small input forks its workers (identification, TRRM, GRRM's helper) as a large one
#: does. As in the console script, rotonly_cli.console (the Ctrl-C handler) is imported first, and a
#: Ctrl-C while the CLI is imported is answered as there
RUN = """if True:
    import sys
    minimum = int(sys.argv.pop(1))
    sys.argv[0] = "rotonly"
    from rotonly_cli import console
    try:
        from rotonly_cli import cli
    except (KeyboardInterrupt, MemoryError) as exc:
        console.start_up_failed(exc)
    group_main = cli.cli.main

    def with_minimum(*args, **kwargs):
        from rotonly_cli.runtime import parallel
        parallel.MIN_MATCHES_PER_JOB = minimum
        return group_main(*args, **kwargs)

    cli.cli.main = with_minimum
    console.main()
"""
#: how long the processes of a run may take to end after its main process did
ORPHAN_GRACE_S = 3.0


def members(group: int) -> list[int]:
    """Live (not zombie) processes of process group ``group``."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as stat:
                fields = stat.read().rsplit(b")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if int(fields[2]) == group and fields[0] != b"Z":
            found.append(int(entry))
    return found


@dataclass
class Run:
    """A `rotonly` process started in a group of its own, its stdout and stderr in files."""

    process: subprocess.Popen
    stderr_path: Path
    started: float = field(default_factory=time.monotonic)

    @property
    def pid(self) -> int:
        return self.process.pid

    def workers(self) -> list[int]:
        """The run's other live processes (the ones it forked)."""
        return [pid for pid in members(self.pid) if pid != self.pid]

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace")


def start(args: list, tmpdir: Path, min_matches_per_job: int = 20_000) -> Run:
    """``rotonly ARGS`` with $TMPDIR ``tmpdir``, as the leader of a new process group."""
    handle, name = tempfile.mkstemp(prefix="rotonly-stderr-", suffix=".txt")
    os.close(handle)
    with open(name, "wb") as stderr:
        process = subprocess.Popen([sys.executable, "-c", RUN, str(min_matches_per_job), *map(str, args)],
                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr,
                                   start_new_session=True, cwd=REPOSITORY,
                                   env={**os.environ, "TMPDIR": str(tmpdir), "PYTHONPATH": str(REPOSITORY)})
    return Run(process, Path(name))


@dataclass
class Outcome:
    code: int | None  #: None: the run did not end within the time allowed (then killed)
    stderr: str
    orphans: list[int]  #: processes of the run still alive ORPHAN_GRACE_S after it ended (then killed)
    orphan_free_after_s: float  #: how long after the run's end its last other process was gone


def finish(run: Run, timeout: float = 600.0) -> Outcome:
    """Wait (at most ``timeout`` s) for the run to end, then up to ORPHAN_GRACE_S for every
    process of its group; whatever is left is reported and killed. Never waits longer."""
    try:
        code = run.process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        code = None
        _kill_group(run.pid)
        run.process.wait(timeout=30)
    ended = time.monotonic()
    left = members(run.pid)
    while left and time.monotonic() - ended < ORPHAN_GRACE_S:
        time.sleep(0.02)
        left = members(run.pid)
    gone_after = time.monotonic() - ended
    if left:
        _kill_group(run.pid)
    stderr = run.stderr()
    run.stderr_path.unlink(missing_ok=True)
    return Outcome(code, stderr, left, gone_after)


def _kill_group(group: int) -> None:
    try:
        os.killpg(group, signal.SIGKILL)
    except ProcessLookupError:
        pass
