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


def setup_logging(verbosity: int) -> None:
    level = {-1: logging.WARNING, 0: logging.INFO}.get(verbosity, logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr, force=True)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="rotonly")
@click.option("-v", "--verbose", count=True, help="More log output (-v debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """rotonly: rotation-only SfM (TRRM two-view and GRRM multi-view rotation estimation).

    Reads OpenMVG projects or COLMAP databases, writes OpenMVG sfm_data.json and COLMAP models.
    """
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = -1 if quiet else verbose
    setup_logging(ctx.obj["verbosity"])


#: errno values of an OSError that are about the destination a command writes, not a bug:
#: reported in one line (commands that know their output name it themselves, errors.write_error)
DESTINATION_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM}
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is Ctrl-C, or what a library made of it (click's Abort; pycolmap turns
    a KeyboardInterrupt during its import into RuntimeError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def main(argv: list[str] | None = None) -> None:
    """Console-script entry: maps rotonly's typed errors to one line and an exit code
    (architecture.md "Exit codes"); Ctrl-C to one line and 130. Other exceptions are bugs
    and keep their traceback."""
    try:
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
    except OSError as exc:
        if exc.errno not in DESTINATION_ERRORS or _interrupted(exc):
            raise
        error = write_error(exc, exc.filename or "output", field=None)
        click.echo(f"error: {error}", err=True)
        sys.exit(error.exit_code)
    except BaseException as exc:  # noqa: BLE001 - only Ctrl-C is answered here, the rest re-raised
        if not _interrupted(exc):
            if isinstance(exc, click.exceptions.Abort):
                click.echo("Aborted.", err=True)
                sys.exit(1)
            raise
        click.echo("error: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    sys.exit(0)


def console_main() -> None:
    """The ``rotonly`` console script: :func:`main` in a process that ends right after it.

    Before the interpreter shuts down, every object the run left is frozen (``gc.freeze``):
    otherwise shutdown runs one full garbage collection over all of them and over the imported
    modules, a noticeable part of a small run (docs/tuning.md). Exit handlers still run, and
    outputs are closed by then (atomic writes). In-process callers (the tests) use
    :func:`main`, which freezes nothing.

    Before ``main``, numpy submodules that no command needs at start-up are registered as
    lazily loaded (:mod:`rotonly_cli.runtime.startup`). Ctrl-C during that start-up is
    answered like one during the command (one line, exit 130)."""
    try:
        from rotonly_cli.runtime.startup import defer_unused_numpy_submodules

        defer_unused_numpy_submodules()
    except KeyboardInterrupt:
        click.echo("error: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    try:
        main()
    finally:
        gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    console_main()
