"""The ``terrastream`` command: wires the tiler, streamer and renderer; no logic of its own.

:func:`build_app` makes the Typer app and calls each command module's ``register(app)``
(:data:`cli.commands.COMMANDS`); importing a command module registers nothing by itself.
Every command gets :class:`cli.common.Command` (one-line errors, exit statuses 1/2/130, readable
help) unless it asks for another class.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from typing import Annotated

import typer
from typer.core import TyperCommand

from cli.commands import COMMANDS
from cli.common import (
    EXIT_STATUS_HELP,
    Command,
    Group,
    interrupted_exit,
    interrupted_text,
    route_sigterm,
    setup_logging,
)


def version() -> str:
    """The installed terrastream version (``0+unknown`` when run from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("terrastream")
    except PackageNotFoundError:
        return "0+unknown"


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"terrastream {version()}")
        raise typer.Exit()


def _root(
    verbose: Annotated[
        int,
        typer.Option(
            "--verbose",
            "-v",
            count=True,
            help="More of terrastream's logging: -v info, -vv debug (and tracebacks).",
        ),
    ] = 0,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="No warnings or progress (results still print).")
    ] = False,
    show_version: Annotated[
        bool,
        typer.Option(
            "--version",
            callback=_print_version,
            is_eager=True,
            help="Print the version and exit.",
        ),
    ] = False,
) -> None:
    setup_logging(verbose, quiet)


def build_app() -> typer.Typer:
    """A new ``terrastream`` app with every command of :data:`cli.commands.COMMANDS`."""
    new = typer.Typer(
        name="terrastream",
        help="Out-of-core terrain: tile DEMs into zarr stores, stream and render them.",
        epilog=EXIT_STATUS_HELP,
        cls=Group,
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    new.callback()(_root)
    for module in COMMANDS:
        module.register(new)
    for info in new.registered_commands:
        if info.cls in (None, TyperCommand):
            info.cls = Command
    return new


app = build_app()


def leave_hung_reads(code: int | str | None) -> None:
    """End the process now with ``code`` (as ``sys.exit`` takes it) if loader threads are still
    blocked in reads a server never answered. They are daemons (:mod:`streamer.pool`), so the
    interpreter would not wait for them either; this also skips finalizing it under reads that
    may still complete. The command has finished with them: ``stream``
    and ``flythrough`` report them and exit 1 (:func:`streamer.run.flight_problem`); any
    other command has written what it draws by then. Output is flushed first."""
    loader = sys.modules.get("streamer.loader")
    hung = loader.threads_alive() if loader is not None else []
    if not hung:
        return
    logging.getLogger("terrastream").debug(
        "leaving %d read thread(s) the server never answered: %s", len(hung), ", ".join(hung)
    )
    if code is not None and not isinstance(code, int):  # sys.exit("message")
        sys.stderr.write(f"{code}\n")
        code = 1
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    logging.shutdown()
    os._exit(code or 0)


def main() -> None:
    """Console entry point."""
    route_sigterm()
    try:
        app()
    except KeyboardInterrupt:  # outside a command (while parsing, say)
        sys.stderr.write(interrupted_text() + "\n")
        leave_hung_reads(interrupted_exit())
        sys.exit(interrupted_exit())
    except SystemExit as exc:
        leave_hung_reads(exc.code)
        raise


if __name__ == "__main__":
    main()
