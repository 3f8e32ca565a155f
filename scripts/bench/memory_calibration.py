"""Calibrate the memory guard (rotonly_cli/runtime/memory.py): run `rotonly run` in this
process, as the console script does, with the guard measuring each stage's peak RSS (VmHWM
reset before each stage through /proc/self/clear_refs, as scripts/bench/scale.py), and print
per stage the counts, the predicted and the measured peak and their ratio.

Usage: python scripts/bench/memory_calibration.py DATABASE [-o OUT] [--jobs N] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from rotonly_cli.runtime import startup

startup.rotonly_process_settings()  # before numpy is imported, as cli.console_main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input", type=Path)
    parser.add_argument("-o", "--output", type=Path, default=None, help="workspace (default: a temporary one)")
    parser.add_argument("--jobs", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--no-limit", action="store_true", help="predict and measure, never stop (recalibrating "
                        "a table that predicts too much)")
    args = parser.parse_args(argv)

    from rotonly_cli import pipeline
    from rotonly_cli.options import RunOptions
    from rotonly_cli.runtime import memory
    from rotonly_cli.runtime.parallel import usable_cpus

    memory.MEASURE_PEAKS = True
    if args.no_limit:
        memory.Limit.in_force = staticmethod(lambda max_memory_gb: memory.Limit(None, "no limit (calibration)"))
    guards = []
    original = memory.MemoryGuard.__init__

    def capture(self, *a, **k):
        original(self, *a, **k)
        guards.append(self)

    memory.MemoryGuard.__init__ = capture
    with tempfile.TemporaryDirectory(prefix="rotonly_memcal_") as tmp:
        out = args.output or Path(tmp) / "out"
        pipeline.run_pipeline(args.input, out, RunOptions(jobs=args.jobs or usable_cpus()))
    rows = [p.record() for p in guards[0].predictions]
    print(f"{'stage':<12} {'matches':>9} {'obs':>9} {'pairs':>11} {'predicted GB':>12} {'measured GB':>11} "
          f"{'ratio':>6}")
    for row in rows:
        c, measured = row["counts"], row.get("measured_gb") or float("nan")
        print(f"{row['stage']:<12} {c['matches']:>9} {c['observations']:>9} {c['pairs']:>11} "
              f"{row['predicted_gb']:>12.3f} {measured:>11.3f} {row['predicted_gb'] / measured:>6.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
