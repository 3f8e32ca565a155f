"""docs/results.md: one section per benchmark, written by the benchmark itself.

Every benchmark command takes ``--results-md FILE``. It then writes its table into FILE as a
section between ``<!-- results:KEY -->`` and ``<!-- /results:KEY -->``: a title, the command
as it was run, the date and the machine, then the table. A rerun replaces its own section and
leaves the others; a new section goes at the end. The file is written atomically.
"""

from __future__ import annotations

import datetime
import os
import platform
import re
import shlex
import sys
from pathlib import Path

from rotonly_cli.io import atomic

HEADER = """# Results

Written by the benchmark commands (`--results-md docs/results.md`); each section says the
command that wrote it and when. A rerun replaces its section: do not edit by hand. The
reasons behind the defaults are in [tuning.md](tuning.md).
"""


def command_line(program: str, argv: list[str] | None = None) -> str:
    """The command as a user would type it: ``program`` and the arguments (``sys.argv[1:]``)."""
    return shlex.join([*program.split(), *(sys.argv[1:] if argv is None else argv)])


def machine() -> str:
    """CPUs, processor and load average: timings depend on them."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    load = f", load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    processor = platform.processor() or platform.machine()
    return f"{cpus} CPUs ({processor}){load}"


def demote_headings(body: str) -> str:
    """The body's own ``#`` / ``##`` headings as ``###``: they sit under the section's title."""
    return re.sub(r"^#{1,2} ", "### ", body, flags=re.M)


def section(key: str, title: str, command: str, body: str, date: datetime.date | None = None) -> str:
    date = date or datetime.date.today()
    return (f"<!-- results:{key} -->\n## {title}\n\n`{command}`  \n{date.isoformat()}, {machine()}\n\n"
            f"{demote_headings(body.strip())}\n<!-- /results:{key} -->\n")


def replace_section(document: str, key: str, new_section: str) -> str:
    """``document`` with the section ``key`` replaced by ``new_section`` (appended if absent)."""
    pattern = re.compile(rf"<!-- results:{re.escape(key)} -->\n.*?<!-- /results:{re.escape(key)} -->\n",
                         re.DOTALL)
    if pattern.search(document):
        return pattern.sub(lambda _: new_section, document, count=1)
    return document.rstrip("\n") + "\n\n" + new_section


def record(path: str | os.PathLike | None, key: str, title: str, command: str, body: str) -> Path | None:
    """Write the section ``key`` into ``path`` (a no-op for None); returns the path written."""
    if path is None:
        return None
    path = Path(path)
    document = path.read_text(encoding="utf-8") if path.is_file() else HEADER
    atomic.write_text(path, replace_section(document, key, section(key, title, command, body)))
    return path


def strip_title(table: str) -> str:
    """A benchmark's table.md without its leading ``# title`` line (the section has one)."""
    lines = table.strip().splitlines()
    while lines and (lines[0].startswith("# ") or not lines[0].strip()):
        lines.pop(0)
    return "\n".join(lines)
