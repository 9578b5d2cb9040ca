"""``terrastream info``: describe a store."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.checks import is_local, not_a_store, open_store_arg
from cli.common import fail_on_errors
from cli.formatters import format_info, json_nodata, json_text
from cli.options import StorageOptionsOpt, store_location


def info(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    storage_options: StorageOptionsOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """Describe a store: blocks, levels, bytes per level, ratio to raw, CRS, extent, values.

    Example: terrastream info n44.zarr
    """
    from tiler.info import store_info

    with fail_on_errors():
        if is_local(store) and not Path(store).exists():
            open_store_arg(store)  # the usage error
        location = store_location(store, storage_options)  # options on a path: usage error
        not_a_store(store)
        d = store_info(location)
        if as_json:
            # (strict JSON: a NaN nodata is the string "nan", other non-finite values null)
            typer.echo(json_text(d | {"nodata": json_nodata(d.get("nodata"))}, indent=2))
            return
        typer.echo(format_info(d))


def register(app: typer.Typer) -> None:
    """Add ``info`` to ``app``."""
    app.command("info")(info)
