"""``terrastream info``: describe a store."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.formatters import format_info


def info(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """Describe a store: blocks, levels, bytes per level, ratio to raw, CRS, extent, values.

    Example: terrastream info n44.zarr
    """
    from tiler.info import store_info

    with fail_on_errors():
        d = store_info(store)
        if as_json:
            typer.echo(json.dumps(d, indent=2))
            return
        typer.echo(format_info(d))


def register(app: typer.Typer) -> None:
    """Add ``info`` to ``app``."""
    app.command("info")(info)
