#!/usr/bin/env python3
"""Interrupt `rotonly run` at many moments and check what OUT and its folder hold (issue 21).

* kill -9 at ``--kills`` moments spread over a whole run (start-up included): after each,
  OUT must be the previous workspace or the new one, complete; then a normal run into the
  same OUT must leave no staging folder of the killed run behind (nor anything in $TMPDIR);
* SIGINT (Ctrl-C) at ``--interrupts`` moments: exit 130 with one line (or 0 if the run was
  done), OUT the previous workspace or the new one, complete, and nothing left at once;
* ``--concurrent`` pairs of runs started together into one OUT: both exit 0 (or one with a
  one-line message), OUT one complete workspace, nothing left beside it.

    python scripts/faults/interrupt_runs.py                       # the 4-image fixture database
    python scripts/faults/interrupt_runs.py --input DB --kills 20 --interrupts 10 --concurrent 5

Prints one line per trial and the counts; exit code 0 when every trial is clean.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]
DEFAULT_INPUT = REPOSITORY / "data_fixtures" / "colmap38_herzjesu4" / "database.db"
RUN = "from rotonly_cli.cli import console_main; console_main()"
WORKSPACE_FILES = ("sfm_data.json", "view_graph.json", "run.log", "state.npz", "sparse/cameras.bin",
                   "sparse/images.bin", "sparse/points3D.bin", "reports/run.json")
PREVIOUS = "PREVIOUS WORKSPACE"


def start(input_path: Path, out: Path, tmpdir: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", RUN, "-q", "run", str(input_path), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "TMPDIR": str(tmpdir)})


def finish(process: subprocess.Popen) -> tuple[int, str]:
    _, err = process.communicate(timeout=900)
    return process.returncode, err


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


def timed_run(input_path: Path, out: Path, tmpdir: Path) -> tuple[int, str, float]:
    begin = time.monotonic()
    code, err = finish(start(input_path, out, tmpdir))
    return code, err, time.monotonic() - begin


def interrupt(input_path: Path, out: Path, tmpdir: Path, delay: float, signal_number: int) -> tuple[int, str]:
    """A run into OUT (the previous workspace marked) sent ``signal_number`` after ``delay`` s."""
    mark_previous(out)
    process = start(input_path, out, tmpdir)
    time.sleep(delay)
    process.send_signal(signal_number)
    return finish(process)


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
        interrupt(input_path, out, tmpdir, delay, signal.SIGKILL)
        after_kill, left = state_of(out), leftovers(out, tmpdir)
        code, err, _ = timed_run(input_path, out, tmpdir)
        after_next, left_next = state_of(out), leftovers(out, tmpdir)
        clean = after_kill in ("previous", "new") and code == 0 and after_next == "new" and not left_next
        tally.add(after_kill, clean, f"kill -9 at {delay:5.2f} s: OUT {after_kill}, {len(left)} left beside it; next "
                                     f"run exit {code}, OUT {after_next}, left {left_next or 'nothing'} {err[-300:]}")
    return tally.result


def interrupts(input_path: Path, out: Path, tmpdir: Path, duration: float, count: int) -> dict:
    tally = Tally(count)
    for k in range(1, count + 1):
        delay = duration * k / (count + 1)
        code, err = interrupt(input_path, out, tmpdir, delay, signal.SIGINT)
        after, left = state_of(out), leftovers(out, tmpdir)
        lines = err.strip().splitlines()
        one_line = code == 0 or (code == 130 and lines == ["error: interrupted"])
        clean = after in ("previous", "new") and not left and one_line and (code == 0) == (after == "new")
        tally.add(f"exit {code}, OUT {after}", clean,
                  f"SIGINT at {delay:5.2f} s: exit {code}, OUT {after}, left {left or 'nothing'}, stderr {lines}")
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
        results = [finish(process) for process in runs]
        codes = [code for code, _ in results]
        after, left = state_of(out), leftovers(out, tmpdir)
        messages_ok = all(code == 0 or len(err.strip().splitlines()) == 1 for code, err in results)
        clean = after == "new" and not left and messages_ok and codes.count(0) >= 1
        tally.add(f"exits {sorted(codes)}, OUT {after}", clean,
                  f"two runs at once{' over a workspace' if k % 2 else ''}: exits {codes}, OUT {after}, "
                  f"left {left or 'nothing'}" + ("" if clean else f" {results}"))
    return tally.result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, default=DEFAULT_INPUT, help="INPUT of the runs (a database)")
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--interrupts", type=int, default=10)
    parser.add_argument("--concurrent", type=int, default=4)
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    args = parser.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="rotonly-faults-", dir=args.work))
    tmpdir = root / "tmpdir"
    tmpdir.mkdir()
    try:
        out = root / "out"
        code, err, duration = timed_run(args.input.resolve(), out, tmpdir)
        if code != 0:
            print(err, file=sys.stderr)
            return 1
        _, _, duration = timed_run(args.input.resolve(), out, tmpdir)  # over a workspace: the timed case
        print(f"one run: {duration:.2f} s; interrupting at {args.kills} + {args.interrupts} moments within it")
        summary = {"kill -9": kills(args.input.resolve(), out, tmpdir, duration, args.kills),
                   "SIGINT": interrupts(args.input.resolve(), out, tmpdir, duration, args.interrupts),
                   "concurrent": concurrent(args.input.resolve(), root, tmpdir, args.concurrent)}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print()
    for name, result in summary.items():
        print(f"{name}: {result['trials']} trials, {result['failures']} not clean; outcomes {result['outcomes']}")
    return 1 if any(result["failures"] for result in summary.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
