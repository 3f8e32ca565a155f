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
reasons behind the defaults are in [tuning.md](tuning.md). In the commands, `DATA` is the
folder of your data (`DATA/strecha`: the Strecha scenes), `OPENMVG_BIN` OpenMVG's `bin`
folder and `RESULTS` an output folder of your choice; other paths are relative to the
repository.
"""

#: how an absolute path outside the working folder is written, by the option it follows; the
#: others become ``DATA/...`` (:func:`portable_path`)
PLACEHOLDERS = {"-o": "RESULTS", "--output": "RESULTS", "--openmvg-bin": "OPENMVG_BIN", "--cache": "CACHE"}


def portable_path(value: str, option: str | None, cwd: Path | None = None) -> str:
    """``value`` as any user can type it: an absolute path below ``cwd`` relative to it, another
    absolute path the placeholder of ``option`` (:data:`PLACEHOLDERS`), else ``DATA/`` and its
    part below a folder named ``data`` (``/srv/data/strecha/fountain-P11`` ->
    ``DATA/strecha/fountain-P11``), else ``DATA/`` and its name. Anything else as given."""
    if not os.path.isabs(value):
        return value
    path, cwd = Path(value), Path.cwd() if cwd is None else cwd
    if path == cwd or cwd in path.parents:
        return os.path.relpath(path, cwd)
    if option in PLACEHOLDERS:
        return PLACEHOLDERS[option]
    parts = path.parts
    below = max((k for k, part in enumerate(parts[:-1]) if part.lower() == "data"), default=None)
    return "/".join(["DATA", *(parts[below + 1:] if below is not None else parts[-1:])])


def command_line(program: str, argv: list[str] | None = None, cwd: Path | None = None) -> str:
    """The command as a user would type it: ``program`` and the arguments (``sys.argv[1:]``),
    one machine's absolute folders written as :func:`portable_path`."""
    args, option = [], None
    for arg in sys.argv[1:] if argv is None else argv:
        if arg.startswith("-") and "=" in arg:
            name, value = arg.split("=", 1)
            args.append(f"{name}={portable_path(value, name, cwd)}")
        else:
            args.append(portable_path(arg, option, cwd))
        option = arg if arg.startswith("-") else None
    return shlex.join([*program.split(), *args])


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
