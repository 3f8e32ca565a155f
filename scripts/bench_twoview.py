#!/usr/bin/env python
"""Two-view Monte-Carlo benchmark: folded into ``rotonly bench twoview`` (rotonly_cli/bench/twoview.py).

This shim keeps the old entry point: it forwards its arguments to the CLI, e.g.

    python scripts/bench_twoview.py -o /tmp/bench_twoview --quick
    python scripts/bench_twoview.py -o /tmp/bench_twoview --trials 500 --jobs 2
"""

from __future__ import annotations

import sys

from rotonly_cli.cli import main

if __name__ == "__main__":
    main(["bench", "twoview", *sys.argv[1:]])
