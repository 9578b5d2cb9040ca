"""The ``terrastream`` command: wires the tiler, streamer and renderer; no logic of its own.

:func:`build_app` makes the Typer app and calls each command module's ``register(app)``
(:data:`cli.commands.COMMANDS`); importing a command module registers nothing by itself.
"""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer

from cli.commands import COMMANDS
from cli.common import setup_logging


def _root(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="More logging.")] = 0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only errors.")] = False,
) -> None:
    setup_logging(verbose, quiet)


def build_app() -> typer.Typer:
    """A new ``terrastream`` app with every command of :data:`cli.commands.COMMANDS`."""
    new = typer.Typer(
        name="terrastream",
        help="Out-of-core terrain: tile DEMs into zarr stores, stream and render them.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    new.callback()(_root)
    for module in COMMANDS:
        module.register(new)
    return new


app = build_app()


def main() -> None:
    """Console entry point."""
    try:
        app()
    except KeyboardInterrupt:
        logging.getLogger("terrastream").error("interrupted")
        sys.stderr.write(
            "interrupted: nothing finished was lost; rerun the same command to continue\n"
        )
        sys.exit(130)


if __name__ == "__main__":
    main()
