"""Small helpers shared by the CLI commands: logging, error reporting, formatting."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

import typer

EXIT_USER_ERROR = 2


def setup_logging(verbose: int, quiet: bool) -> None:
    """Map ``-v``/``-q`` to log levels (warning by default)."""
    level = (
        logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    )
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)


@contextmanager
def fail_on_errors() -> Iterator[None]:
    """Turn the packages' own errors into ``error: …`` on stderr and exit status 2."""
    try:
        yield
    except known_errors() as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EXIT_USER_ERROR) from exc


def known_errors() -> tuple[type[BaseException], ...]:
    """Error classes whose message is meant for the user (no traceback)."""
    import importlib

    out: list[type[BaseException]] = []
    for mod, name in (
        ("tiler.errors", "TilerError"),
        ("streamer.errors", "StreamerError"),
        ("render.errors", "RenderError"),
    ):
        try:
            out.append(getattr(importlib.import_module(mod), name))
        except (ImportError, AttributeError):
            continue
    return tuple(out)
