#!/usr/bin/env python3
"""Interrupt `rotonly run` at many moments and check what OUT and its folder hold (issue 21).

* kill -9 at ``--kills`` moments spread over a whole run (start-up included): after each,
  OUT must be the previous workspace or the new one, complete; then a normal run into the
  same OUT must leave no staging folder of the killed run behind (nor anything in $TMPDIR);
* SIGINT (Ctrl-C) at ``--interrupts`` random moments of a run (``--seed``): exit 130 with one
  line and OUT as before, or exit 0 with OUT new (the Ctrl-C came once the commit had begun),
  never 130 with OUT new, never a lost Ctrl-C (a KeyboardInterrupt printed and ignored), and
  nothing left at once;
* ``--concurrent`` pairs of runs started together into one OUT: both exit 0 (or one with a
  one-line message), OUT one complete workspace, nothing left beside it.

    python scripts/faults/interrupt_runs.py                       # the 4-image fixture database
    python scripts/faults/interrupt_runs.py --input DB --kills 20 --interrupts 10 --concurrent 5

Every run is a process group of its own (processes.py): a process of it still alive 3 s after
it ended is an orphan, reported (and killed), and no wait is unbounded. Prints one line per
trial and the counts; exit code 0 when every trial is clean.
"""

from __future__ import annotations

import argparse
import random
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

import processes

REPOSITORY = processes.REPOSITORY
DEFAULT_INPUT = REPOSITORY / "data_fixtures" / "colmap38_herzjesu4" / "database.db"
#: runtime.parallel.MIN_MATCHES_PER_JOB of the runs (--min-matches-per-job; 500: the fixture forks
#: its workers as a large input does, so that the faults meet them)
MIN_MATCHES_PER_JOB = [500]
#: longest a run may take before it is killed and counted as hung
TIMEOUT_S = 900.0
WORKSPACE_FILES = ("sfm_data.json", "view_graph.json", "run.log", "state.npz", "sparse/cameras.bin",
                   "sparse/images.bin", "sparse/points3D.bin", "reports/run.json")
PREVIOUS = "PREVIOUS WORKSPACE"


def start(input_path: Path, out: Path, tmpdir: Path) -> processes.Run:
    return processes.start(["-q", "run", input_path, "-o", out], tmpdir, MIN_MATCHES_PER_JOB[0])


def finish(run: processes.Run) -> processes.Outcome:
    return processes.finish(run, TIMEOUT_S)


def state_of(out: Path) -> str:
    """'previous', 'new', 'absent' or 'PARTIAL (...)'."""
    if not out.exists():
        return "absent"
    missing = [name for name in WORKSPACE_FILES if not (out / name).is_file()]
    if missing:
        return f"PARTIAL (missing {', '.join(missing)})"
    from rotonly_cli.errors import InputError
    from rotonly_cli.io.workspace import load_state

    try:
        load_state(out)
    except InputError as exc:
        return f"PARTIAL ({exc})"
    return "previous" if PREVIOUS in (out / "run.log").read_text(errors="replace") else "new"


def leftovers(out: Path, tmpdir: Path) -> list[str]:
    beside = [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]
    return sorted(beside + [f"$TMPDIR/{p.name}" for p in tmpdir.iterdir()])


def mark_previous(out: Path) -> None:
    with open(out / "run.log", "a") as log:
        log.write(f"{PREVIOUS}\n")


def timed_run(input_path: Path, out: Path, tmpdir: Path) -> tuple[processes.Outcome, float]:
    begin = time.monotonic()
    outcome = finish(start(input_path, out, tmpdir))
    return outcome, time.monotonic() - begin


def interrupt(input_path: Path, out: Path, tmpdir: Path, delay: float,
              signal_number: int) -> tuple[processes.Outcome, str]:
    """A run into OUT (the previous workspace marked) sent ``signal_number`` after ``delay`` s:
    (its outcome, OUT's state just before the signal)."""
    mark_previous(out)
    run = start(input_path, out, tmpdir)
    time.sleep(delay)
    before = state_of(out)
    run.process.send_signal(signal_number)
    return finish(run), before


class Tally:
    """Outcome counts and failures of one kind of trial; prints one line per trial."""

    def __init__(self, count: int):
        self.result = {"trials": count, "outcomes": {}, "failures": 0}

    def add(self, outcome: str, clean: bool, line: str) -> None:
        self.result["outcomes"][outcome] = self.result["outcomes"].get(outcome, 0) + 1
        self.result["failures"] += not clean
        print(line + ("" if clean else "  <-- NOT CLEAN"))


def kills(input_path: Path, out: Path, tmpdir: Path, duration: float, count: int) -> dict:
    tally = Tally(count)
    for k in range(1, count + 1):
        delay = duration * k / (count + 1)
        killed, _ = interrupt(input_path, out, tmpdir, delay, signal.SIGKILL)
        after_kill, left = state_of(out), leftovers(out, tmpdir)
        after, _ = timed_run(input_path, out, tmpdir)
        after_next, left_next = state_of(out), leftovers(out, tmpdir)
        orphans = killed.orphans + after.orphans
        clean = after_kill in ("previous", "new") and after.code == 0 and after_next == "new" and not left_next \
            and not orphans
        tally.add(after_kill, clean, f"kill -9 at {delay:5.2f} s: OUT {after_kill}, {len(left)} left beside it, "
                                     f"{len(killed.orphans)} processes alive 3 s later; next run exit {after.code}, "
                                     f"OUT {after_next}, left {left_next or 'nothing'} {after.stderr[-300:]}")
    return tally.result


def interrupts(input_path: Path, out: Path, tmpdir: Path, duration: float, count: int, seed: int) -> dict:
    tally = Tally(count)
    moments = random.Random(seed).uniform  # the same moments for the same seed
    for _ in range(count):
        delay = moments(0.0, duration)
        outcome, before = interrupt(input_path, out, tmpdir, delay, signal.SIGINT)
        after, left = state_of(out), leftovers(out, tmpdir)
        lines = outcome.stderr.strip().splitlines()
        lost = "Exception ignored" in outcome.stderr or "KeyboardInterrupt" in outcome.stderr
        one_line = (outcome.code == 0 and not lines) or (outcome.code == 130 and lines == ["error: interrupted"])
        clean = after in ("previous", "new") and not left and one_line and not lost and not outcome.orphans \
            and (outcome.code == 0) == (after == "new")
        tally.add(f"exit {outcome.code}, OUT {after}", clean,
                  f"SIGINT at {delay:5.2f} s (OUT {before} then): exit {outcome.code}, OUT {after}, left "
                  f"{left or 'nothing'}, {len(outcome.orphans)} processes alive 3 s later, stderr {lines[-3:]}")
    return tally.result


def concurrent(input_path: Path, root: Path, tmpdir: Path, count: int) -> dict:
    tally = Tally(count)
    for k in range(count):
        out = root / f"concurrent{k}" / "out"
        out.parent.mkdir()
        if k % 2:  # every other pair replaces an existing workspace
            shutil.copytree(root / "out", out)
            mark_previous(out)
        runs = [start(input_path, out, tmpdir) for _ in range(2)]
        results = [finish(run) for run in runs]
        codes = [result.code for result in results]
        after, left = state_of(out), leftovers(out, tmpdir)
        messages_ok = all(r.code == 0 or len(r.stderr.strip().splitlines()) == 1 for r in results)
        orphans = sum(len(r.orphans) for r in results)
        clean = after == "new" and not left and messages_ok and codes.count(0) >= 1 and not orphans
        tally.add(f"exits {sorted(codes, key=str)}, OUT {after}", clean,
                  f"two runs at once{' over a workspace' if k % 2 else ''}: exits {codes}, OUT {after}, "
                  f"left {left or 'nothing'}, {orphans} orphans" + ("" if clean else f" {[r.stderr for r in results]}"))
    return tally.result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=DEFAULT_INPUT, help="INPUT of the runs (a database)")
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--interrupts", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0, help="of the random moments of the Ctrl-C")
    parser.add_argument("--concurrent", type=int, default=4)
    parser.add_argument("--min-matches-per-job", type=int, default=MIN_MATCHES_PER_JOB[0],
                        help="runtime.parallel.MIN_MATCHES_PER_JOB of the runs (20000: rotonly's own)")
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    args = parser.parse_args(argv)
    MIN_MATCHES_PER_JOB[0] = args.min_matches_per_job
    root = Path(tempfile.mkdtemp(prefix="rotonly-faults-", dir=args.work))
    tmpdir = root / "tmpdir"
    tmpdir.mkdir()
    try:
        out = root / "out"
        first, duration = timed_run(args.input.resolve(), out, tmpdir)
        if first.code != 0:
            print(first.stderr, file=sys.stderr)
            return 1
        _, duration = timed_run(args.input.resolve(), out, tmpdir)  # over a workspace: the timed case
        print(f"one run: {duration:.2f} s; interrupting at {args.kills} + {args.interrupts} moments within it")
        summary = {"kill -9": kills(args.input.resolve(), out, tmpdir, duration, args.kills),
                   "SIGINT": interrupts(args.input.resolve(), out, tmpdir, duration, args.interrupts, args.seed),
                   "concurrent": concurrent(args.input.resolve(), root, tmpdir, args.concurrent)}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print()
    for name, result in summary.items():
        print(f"{name}: {result['trials']} trials, {result['failures']} not clean; outcomes {result['outcomes']}")
    return 1 if any(result["failures"] for result in summary.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
