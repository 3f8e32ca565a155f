"""The ``rotonly`` console script (pyproject.toml ``[project.scripts]``).

This module's first statement puts the CLI's Ctrl-C handler in place (runtime/interrupts),
before the command-line module and what it imports (click, the option tables: about 50 ms of
start-up) are loaded. A Ctrl-C from then on is answered like one during the command: one line,
exit 130, OUT as it was (issue 53). Before it, only the interpreter's own start-up is left:
there a Ctrl-C ends Python with its own traceback (killed by SIGINT: 130 in a shell), or, while
``site`` runs the installed ``.pth`` files, with "Fatal Python error" and exit 1 — outside what
a Python program can catch (docs/architecture.md "Exit codes").
"""

from rotonly_cli.runtime import interrupts

interrupts.install()

EXIT_INTERRUPTED = 130


def main() -> None:
    """``rotonly``: the CLI (:func:`rotonly_cli.cli.console_main`) once it is imported; a Ctrl-C or
    running out of memory while it is imported: one line, like during the command."""
    try:
        from rotonly_cli.cli import console_main
    except (KeyboardInterrupt, MemoryError) as exc:
        start_up_failed(exc)
    console_main()


def start_up_failed(exc: BaseException) -> None:
    import sys

    if isinstance(exc, KeyboardInterrupt):
        sys.stderr.write("error: interrupted\n")
        sys.exit(EXIT_INTERRUPTED)
    sys.stderr.write("error: out of memory while rotonly started\n")
    sys.exit(1)
