"""``terrastream export``: a GeoTIFF rebuilt from a store."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from cli.checks import open_store_arg, output_file
from cli.common import UsageError, fail_on_errors
from cli.options import StorageOptionsOpt, integer, store_location


class ExportFormat(StrEnum):
    """Output formats of ``export``."""

    cog = "cog"
    gtiff = "gtiff"


def export(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    out: Annotated[Path, typer.Argument(help="Output GeoTIFF.")],
    level: Annotated[
        int | None, integer("--level", "Level to export (default: the finest).", min=0)
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUT if it exists.")
    ] = False,
    fmt: Annotated[
        ExportFormat | None,
        typer.Option(
            "--format",
            help="cog: Cloud Optimized GeoTIFF, overviews from the store's coarser levels "
            "(default for .tif/.tiff); gtiff: a plain tiled GeoTIFF.",
        ),
    ] = None,
    storage_options: StorageOptionsOpt = None,
) -> None:
    """Rebuild a GeoTIFF of the whole DEM from a store (bit-identical when lossless).

    Example: terrastream export n44.zarr n44.tif --level 8
    (a COG whose overviews are levels 7, 6, ...; --format gtiff for a plain GeoTIFF)
    """
    from tiler.export import COG_BLOCK, export_cog, export_geotiff

    with fail_on_errors():
        output_file(out, "OUT", suffixes=(".tif", ".tiff"), overwrite=overwrite)
        s = open_store_arg(store_location(store, storage_options))
        if level is not None and not 0 <= level <= s.k:
            raise UsageError(
                f"--level must be in 0..{s.k} for this store, got {level}", hint="--level"
            )
        if fmt is None:
            fmt = (
                ExportFormat.cog if out.suffix.lower() in (".tif", ".tiff") else ExportFormat.gtiff
            )
        if fmt is ExportFormat.cog:
            levels = export_cog(s, out, level)
            ovr = ", ".join(map(str, levels[1:]))
            typer.echo(
                f"wrote {out}: COG of level {levels[0]} of {s.k}, "
                + (
                    f"overviews = levels {ovr}"
                    if ovr
                    else f"no overviews (it fits one {COG_BLOCK}² tile)"
                )
            )
        else:
            export_geotiff(s, out, level)
            typer.echo(f"wrote {out} (level {s.k if level is None else level} of {s.k})")


def register(app: typer.Typer) -> None:
    """Add ``export`` to ``app``."""
    app.command("export")(export)
