#!/usr/bin/env python3
"""kill -9 of `rotonly run`'s main process while its forked workers live (issue 53), as the
kernel's OOM killer does: the workers must die with it, and the next run into OUT must leave
nothing beside OUT.

Each trial starts a run into OUT (a previous workspace), waits until the run has forked its
n-th worker (n = 1 .. --workers: on the fixture identification, TRRM, GRRM's helper, the
sfm_data.json writer) and that worker has lived ``m x --step`` seconds (m = 0, 1, 2, ...
as the trials go round the workers), kills the main process alone with SIGKILL, and counts the run's processes still
alive ``ORPHAN_GRACE_S`` (3 s) later; then a normal run into the same OUT must exit 0 and
leave nothing beside OUT. The runs are process groups of their own: every wait is bounded, and
a survivor is reported and killed, never waited for.

    python scripts/faults/kill_workers.py                        # 12 kills, the 4-image fixture
    python scripts/faults/kill_workers.py --kills 20 --input DB --min-matches-per-job 20000

Prints one line per trial and the counts; exit code 0 when every trial is clean.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

import processes

DEFAULT_INPUT = processes.REPOSITORY / "data_fixtures" / "colmap38_herzjesu4" / "database.db"


def leftovers(out: Path, tmpdir: Path) -> list[str]:
    beside = [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]
    return sorted(beside + [f"$TMPDIR/{p.name}" for p in tmpdir.iterdir()])


def kill_when_a_worker_lived(run: processes.Run, nth: int, lived_s: float, limit_s: float) -> tuple[bool, int]:
    """SIGKILL the run's main process once its ``nth`` worker (1: the first it forked) has been
    alive ``lived_s`` s (should it end before, the next worker takes its place), or when the run
    ends or ``limit_s`` passes: (a worker was alive at the kill, how many)."""
    first_seen: dict[int, float] = {}  # in the order the workers were seen
    deadline = time.monotonic() + limit_s
    while run.process.poll() is None and time.monotonic() < deadline:
        now = time.monotonic()
        workers = run.workers()
        for pid in workers:
            first_seen.setdefault(pid, now)
        if len(first_seen) >= nth:
            pid, seen = list(first_seen.items())[nth - 1]
            if pid not in workers:  # it ended before its time: the kill waits for the next worker
                nth = len(first_seen) + 1
            elif now - seen >= lived_s:
                run.process.send_signal(signal.SIGKILL)
                return True, len(workers)
        time.sleep(0.005)
    run.process.send_signal(signal.SIGKILL)
    return False, 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=DEFAULT_INPUT, help="INPUT of the runs (a database)")
    parser.add_argument("--kills", type=int, default=12)
    parser.add_argument("--workers", type=int, default=4, help="the kill points go round the first this many workers")
    parser.add_argument("--step", type=float, default=0.15, help="seconds a worker lives more at each round")
    parser.add_argument("--min-matches-per-job", type=int, default=500,
                        help="runtime.parallel.MIN_MATCHES_PER_JOB of the runs (default 500: the fixture forks)")
    parser.add_argument("--timeout", type=float, default=600.0, help="longest a run may take (then it is killed)")
    args = parser.parse_args(argv)
    input_path = args.input.resolve()
    root = Path(tempfile.mkdtemp(prefix="rotonly-kill-workers-"))
    tmpdir = root / "tmpdir"
    tmpdir.mkdir()
    out = root / "out"
    counts = {"trials": 0, "with workers alive": 0, "orphans after 3 s": 0, "next run not clean": 0, "hung": 0}
    try:
        first = processes.finish(processes.start(["-q", "run", input_path, "-o", out], tmpdir,
                                                 args.min_matches_per_job), args.timeout)
        if first.code != 0:
            print(first.stderr, file=sys.stderr)
            return 1
        for k in range(args.kills):
            run = processes.start(["-q", "run", input_path, "-o", out], tmpdir, args.min_matches_per_job)
            nth, lived = k % args.workers + 1, k // args.workers * args.step
            alive, workers = kill_when_a_worker_lived(run, nth, lived, args.timeout)
            killed = processes.finish(run, 30)
            left_by_kill = leftovers(out, tmpdir)
            after = processes.finish(processes.start(["-q", "run", input_path, "-o", out], tmpdir,
                                                     args.min_matches_per_job), args.timeout)
            left = leftovers(out, tmpdir)
            clean_next = after.code == 0 and not left and not after.orphans
            counts["trials"] += 1
            counts["with workers alive"] += alive
            counts["orphans after 3 s"] += len(killed.orphans)
            counts["next run not clean"] += not clean_next
            counts["hung"] += after.code is None
            clean = not killed.orphans and clean_next
            print(f"kill {k + 1:2d} (worker {nth} alive {lived:4.2f} s; {workers} workers then): "
                  f"{len(killed.orphans)} alive {processes.ORPHAN_GRACE_S:.0f} s later (all gone after "
                  f"{killed.orphan_free_after_s:.2f} s), {len(left_by_kill)} left beside OUT; next run exit "
                  f"{after.code}, left {left or 'nothing'}" + ("" if clean else "  <-- NOT CLEAN")
                  + ("" if after.code == 0 else f" {after.stderr[-300:]}"))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print()
    print(f"kill -9: {counts['trials']} trials, {counts['with workers alive']} with workers alive at the kill, "
          f"{counts['orphans after 3 s']} processes alive 3 s later, {counts['next run not clean']} next runs "
          f"not clean, {counts['hung']} hung")
    return 0 if counts["orphans after 3 s"] == counts["next run not clean"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
