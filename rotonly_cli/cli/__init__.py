"""`rotonly` command-line entry point: a thin click group.

Subcommands live one per module (``rotonly_cli.cli.<name>``, each exposing ``command``)
and are imported lazily, so ``rotonly --help`` stays fast and a broken optional module
never breaks the others.
"""

from __future__ import annotations

import errno
import gc
import importlib
import logging
import sys
from collections.abc import Iterator

import click

from rotonly_cli import __version__
from rotonly_cli.errors import RotonlyError, write_error

# name -> module; the order is the order shown in --help.
COMMANDS: dict[str, str] = {
    "run": "rotonly_cli.cli.run",
    "identify": "rotonly_cli.cli.stages",
    "refine": "rotonly_cli.cli.refine",
    "average": "rotonly_cli.cli.stages",
    "optimize": "rotonly_cli.cli.stages",
    "translate": "rotonly_cli.cli.stages",
    "reject": "rotonly_cli.cli.stages",
    "triangulate": "rotonly_cli.cli.stages",
    "eval": "rotonly_cli.cli.eval",
    "convert": "rotonly_cli.cli.convert",
    "simulate": "rotonly_cli.cli.simulate",
    "bench": "rotonly_cli.cli.bench",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return [name for name in COMMANDS if self._load(name) is not None]

    def get_command(self, ctx: click.Context, cmd_name: str):
        return self._load(cmd_name)

    @staticmethod
    def _load(name: str):
        module_name = COMMANDS.get(name)
        if module_name is None:
            return None
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:  # a subcommand not built yet
            if exc.name == module_name:
                return None
            raise
        commands = getattr(module, "commands", None)
        if commands is not None:
            return commands.get(name)
        return getattr(module, "command", None)


#: rotonly's own loggers (the package's modules and GRRM's "rotonly.grrm"): -v shows their debug
#: lines, -vv every library's
ROTONLY_LOGGERS = ("rotonly_cli", "rotonly")
#: libraries that log at info level on their own (matplotlib: "generated new fontManager" on a
#: machine's first report): their warnings only, every line with -vv
CHATTY_LIBRARIES = ("matplotlib",)

#: the closing text of every command's --help
EPILOG = """\b
Exit codes: 0 success; 1 no result possible (e.g. fewer than two connected views);
2 bad input or usage (one line names the file and the field; nothing is written).
Shell completion (bash): eval "$(_ROTONLY_COMPLETE=bash_source rotonly)" in ~/.bashrc;
zsh: zsh_source in ~/.zshrc; fish: fish_source into ~/.config/fish/completions/rotonly.fish."""


class _StderrHandler(logging.StreamHandler):
    """The console's log handler: a MemoryError while a record is formatted or written is
    raised to the code that logged (the run then ends with one error line, :func:`main`)
    instead of being printed as a "Logging error" traceback while the run goes on."""

    def handleError(self, record: logging.LogRecord) -> None:
        if isinstance(sys.exc_info()[1], MemoryError):
            raise  # noqa: PLE0704 - called inside emit()'s except block: the error being handled
        super().handleError(record)


def setup_logging(verbosity: int) -> None:
    """-q (-1): warnings and errors; default (0): one line per stage; -v (1): rotonly's per-stage
    detail (edge counts per reason, GRRM iterations, timings) with logger names; -vv: every
    library's debug output too."""
    level = {-1: logging.WARNING, 0: logging.INFO, 1: logging.INFO}.get(verbosity, logging.DEBUG)
    fmt = ("%(asctime)s %(levelname)s %(name)s: %(message)s" if verbosity > 0
           else "%(levelname)s: %(message)s" if verbosity < 0 else "%(asctime)s %(message)s")
    handler = _StderrHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(fmt, datefmt="%H:%M:%S"))
    logging.basicConfig(level=level, handlers=[handler], force=True)
    for name in ROTONLY_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if verbosity > 0 else logging.NOTSET)
    for name in CHATTY_LIBRARIES:
        logging.getLogger(name).setLevel(logging.WARNING if verbosity < 2 else logging.NOTSET)


def _verbosity(ctx: click.Context, **change) -> None:
    """Record -v / -q (given before or after the subcommand) on the root context and set the
    logging up again: ``-q`` wins, ``-v`` counts wherever it stands."""
    state = ctx.find_root().ensure_object(dict)
    state["verbose"] = state.get("verbose", 0) + change.get("verbose", 0)
    state["quiet"] = state.get("quiet", False) or change.get("quiet", False)
    state["verbosity"] = -1 if state["quiet"] else state["verbose"]
    setup_logging(state["verbosity"])


def _on_verbose(ctx: click.Context, param: click.Parameter, value: int) -> None:
    if value and not ctx.resilient_parsing:
        _verbosity(ctx, verbose=value)


def _on_quiet(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value and not ctx.resilient_parsing:
        _verbosity(ctx, quiet=True)


def _on_version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value and not ctx.resilient_parsing:
        click.echo(f"rotonly, version {__version__}")
        ctx.exit()


def global_options() -> list[click.Option]:
    """-v, -q and --version: options of the group and of every subcommand, so that they work
    before and after the subcommand alike."""
    return [
        click.Option(["-v", "--verbose"], count=True, expose_value=False, is_eager=True, callback=_on_verbose,
                     help="More detail: -v per-stage detail (edge counts per reason, GRRM iterations, timings), "
                          "-vv every library's debug output."),
        click.Option(["-q", "--quiet"], is_flag=True, expose_value=False, is_eager=True, callback=_on_quiet,
                     help="Only warnings and errors (no progress bars)."),
        click.Option(["--version"], is_flag=True, expose_value=False, is_eager=True, callback=_on_version,
                     help="Show the version and exit."),
    ]


def with_global_options(command: click.Command) -> click.Command:
    """``command`` (and a group's subcommands) with :func:`global_options` and the exit-code
    epilog; idempotent."""
    if not getattr(command, "_rotonly_global_options", False):
        names = {opt for param in command.params for opt in getattr(param, "opts", ())}
        command.params.extend(option for option in global_options() if not names & set(option.opts))
        command.epilog = command.epilog or EPILOG
        command._rotonly_global_options = True
    for subcommand in getattr(command, "commands", {}).values():
        with_global_options(subcommand)
    return command


class RotonlyGroup(LazyGroup):
    """The lazy group whose subcommands accept the global options too."""

    @staticmethod
    def _load(name: str):
        command = LazyGroup._load(name)
        return None if command is None else with_global_options(command)


@click.group(cls=RotonlyGroup, context_settings={"help_option_names": ["-h", "--help"]}, epilog=EPILOG)
@click.pass_context
def cli(ctx: click.Context) -> None:
    """rotonly: rotation-only SfM (TRRM two-view and GRRM multi-view rotation estimation).

    Reads OpenMVG projects or COLMAP databases, writes OpenMVG sfm_data.json and COLMAP models
    (and OUT/report.html). -v, -q and --version may also follow the subcommand.
    """
    state = ctx.ensure_object(dict)
    if "verbosity" not in state:  # neither -v nor -q given before the subcommand
        _verbosity(ctx)


cli.params.extend(global_options())


#: errno values of an OSError that are about the destination a command writes, not a bug:
#: reported in one line (commands that know their output name it themselves, errors.write_error)
DESTINATION_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM}
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports


def _causes(exc: BaseException | None) -> Iterator[BaseException]:
    """``exc`` and the exceptions it was raised from or while handling (unless suppressed)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        yield exc
        seen.add(id(exc))
        exc = exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is Ctrl-C, or what a library made of it (click's Abort; pycolmap turns
    a KeyboardInterrupt during its import into RuntimeError)."""
    return any(isinstance(cause, KeyboardInterrupt) for cause in _causes(exc))


def _out_of_memory(exc: BaseException) -> BaseException | None:
    """The exception in ``exc``'s chain that says memory ran out, or None: a MemoryError
    (numpy's _ArrayMemoryError, pybind11's std::bad_alloc), ENOMEM (fork, mmap), a thread
    whose stack could not be mapped, a library that could not be mapped under an address-space
    limit; also when a library made another exception of it."""
    for cause in _causes(exc):
        if isinstance(cause, MemoryError) or (isinstance(cause, OSError) and cause.errno == errno.ENOMEM):
            return cause
        if isinstance(cause, RuntimeError) and str(cause) == "can't start new thread":
            return cause
        if isinstance(cause, ImportError) and "failed to map segment" in str(cause):
            return cause
    return None


def out_of_memory_line(exc: BaseException) -> str:
    """``error: <stage> ran out of memory (<the allocation>); it needs about ...`` (runtime/memory:
    the guarded stage the error happened in, and its prediction)."""
    try:
        from rotonly_cli.runtime.memory import LAST_DONE, LAST_STAGE, out_of_memory_error

        if LAST_STAGE[0] is None and LAST_DONE[0] is not None:  # between stages: the last one's need
            return f"error: {out_of_memory_error(None, exc, LAST_DONE[1], after=LAST_DONE[0])}"
        return f"error: {out_of_memory_error(LAST_STAGE[0], exc, LAST_STAGE[1])}"
    except MemoryError:  # not even the module could be imported
        return "error: out of memory"


def main(argv: list[str] | None = None) -> None:
    """Console-script entry: maps rotonly's typed errors to one line and an exit code
    (architecture.md "Exit codes"); Ctrl-C to one line and 130 (0 once the command's output is
    in place: runtime/interrupts); running out of memory, anywhere, to one line and 1
    (runtime/memory). Other exceptions are bugs and keep their traceback."""
    from rotonly_cli.runtime import interrupts
    from rotonly_cli.runtime.invocation import invoked_with

    with interrupts.cli_handling():
        try:
            with invoked_with(sys.argv[1:] if argv is None else argv):
                cli.main(args=argv, prog_name="rotonly", standalone_mode=False)
        except click.exceptions.Exit as exc:
            sys.exit(exc.exit_code)
        except click.ClickException as exc:  # usage: one line too (`rotonly CMD -h` has the rest)
            context = getattr(exc, "ctx", None)
            where = f"{context.command_path}: " if context is not None else ""
            click.echo(f"error: {where}{exc.format_message()}", err=True)
            sys.exit(2)
        except RotonlyError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(exc.exit_code)
        except BaseException as exc:  # noqa: BLE001 - Ctrl-C, memory, a destination: one line; the rest re-raised
            _exit_on(exc, interrupts.written())
        sys.exit(0)


def _exit_on(exc: BaseException, written: bool) -> None:
    """Exit with one line for Ctrl-C (130; 0 when the output was ``written`` already), running
    out of memory (1) and an unusable or full destination; re-raise anything else (a bug, or an
    exit already decided)."""
    if isinstance(exc, SystemExit):
        raise exc
    if _interrupted(exc):
        if written:  # OUT holds the new result: the command succeeded
            sys.exit(0)
        click.echo("error: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    memory_error = _out_of_memory(exc)
    if memory_error is not None:
        click.echo(out_of_memory_line(memory_error), err=True)
        sys.exit(1)
    if isinstance(exc, OSError) and exc.errno in DESTINATION_ERRORS:
        error = write_error(exc, exc.filename or "output", field=None)
        click.echo(f"error: {error}", err=True)
        sys.exit(error.exit_code)
    if isinstance(exc, click.exceptions.Abort):
        click.echo("Aborted.", err=True)
        sys.exit(1)
    raise exc


def console_main() -> None:
    """The ``rotonly`` console script: :func:`main` in a process that ends right after it.

    Before the interpreter shuts down, every object the run left is frozen (``gc.freeze``):
    otherwise shutdown runs one full garbage collection over all of them and over the imported
    modules, a noticeable part of a small run (docs/tuning.md). Exit handlers still run, and
    outputs are closed by then (atomic writes). In-process callers (the tests) use
    :func:`main`, which freezes nothing.

    Before ``main``, BLAS is held to one thread per process, freed heap memory is kept for
    reuse, and numpy submodules that no command needs at start-up are registered as lazily
    loaded (:mod:`rotonly_cli.runtime.startup`). Ctrl-C during that start-up is
    answered like one during the command (one line, exit 130), running out of memory too (one
    line, exit 1). The CLI's Ctrl-C handler stays for the rest of the process
    (runtime/interrupts: after the command's output is written, Ctrl-C is ignored)."""
    try:
        from rotonly_cli.runtime import interrupts, startup

        interrupts.install()
        startup.rotonly_process_settings()  # before numpy is imported
        startup.defer_unused_numpy_submodules()
    except BaseException as exc:  # noqa: BLE001 - Ctrl-C or memory: one line; the rest re-raised
        _exit_on(exc, written=False)
    try:
        main()
    finally:
        gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    console_main()
