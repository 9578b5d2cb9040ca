"""``terrastream tile``: a DEM into a non-redundant level store."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors

Resampling = Enum(
    "Resampling",
    {n: n for n in ("nearest", "bilinear", "cubic", "cubic_spline", "lanczos", "average")},
    type=str,
)


def _sources_and_destination(paths: list[str], from_list: Path | None) -> tuple[list[str], str]:
    """Split ``SRC... DST`` and append the ``--from-list`` file's paths."""
    from tiler.errors import SourceError
    from tiler.source import read_source_list

    if not paths:
        raise typer.BadParameter("give at least a destination store", param_hint="SRC... DST")
    srcs, dst = list(paths[:-1]), paths[-1]
    if from_list is not None:
        try:
            srcs += read_source_list(from_list)
        except SourceError as exc:
            raise typer.BadParameter(str(exc), param_hint="--from-list") from exc
    if not srcs:
        raise typer.BadParameter(
            "give at least one source DEM before the destination (or --from-list FILE)",
            param_hint="SRC... DST",
        )
    return srcs, dst


def tile(
    paths: Annotated[
        list[str],
        typer.Argument(
            help="SRC... DST: source DEMs (any raster rasterio opens; several form one mosaic, "
            "the first listed wins where they overlap) and the destination store.",
            metavar="SRC... DST",
        ),
    ],
    from_list: Annotated[
        Path | None,
        typer.Option("--from-list", help="Text file with more sources, one path per line."),
    ] = None,
    dst_crs: Annotated[
        str | None,
        typer.Option(
            "--dst-crs",
            help="Reproject while tiling: 'auto' (UTM zone of the centre, else a local "
            "projection), EPSG:code, PROJ string or WKT.",
        ),
    ] = None,
    resampling: Annotated[
        Resampling, typer.Option("--resampling", help="Resampling used with --dst-crs.")
    ] = Resampling.bilinear,
    resolution: Annotated[
        float | None,
        typer.Option(
            "--resolution",
            help="Target pixel size in target CRS units (default: the source's finer side).",
        ),
    ] = None,
    block_size: Annotated[
        int, typer.Option("--block-size", help="Block edge in samples, 2^k+1.")
    ] = 1025,
    band: Annotated[int, typer.Option("--band", help="Band to tile (1-based).")] = 1,
    precision: Annotated[
        float | None,
        typer.Option(
            "--precision", help="Float DEMs only: quantise to this step (max error step/2)."
        ),
    ] = None,
    workers: Annotated[
        int, typer.Option("--workers", help="Worker threads (0 = one per core).")
    ] = 0,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing store.")
    ] = False,
    level: Annotated[
        int, typer.Option("--clevel", min=1, max=9, help="Compression level (blosc zstd).")
    ] = 5,
) -> None:
    """Tile a DEM into a non-redundant level store.

    Example: terrastream tile N44W072.hgt n44.zarr --block-size 257

    Several sources form one mosaic: terrastream tile N44W072.hgt N44W073.hgt n44.zarr
    (or --from-list tiles.txt). A geographic DEM (degrees) needs --dst-crs auto to be streamed
    and rendered.
    """
    from tqdm import tqdm

    from tiler.tile import TileOptions, TileProgress
    from tiler.tile import tile as run_tile

    src, dst = _sources_and_destination(paths, from_list)
    with fail_on_errors():
        opts = TileOptions(
            dst_crs=dst_crs,
            resampling=resampling.value,
            resolution=resolution,
            block_size=block_size,
            band=band,
            precision=precision,
            workers=workers,
            overwrite=overwrite,
            compression_level=level,
        )
        bar = tqdm(total=None, unit="block", desc="tiling", disable=None, dynamic_ncols=True)

        def on_progress(p: TileProgress) -> None:
            bar.total = p.blocks_total
            bar.n = p.blocks_done
            rate = p.bytes_done / max(p.elapsed_s, 1e-9) / 1e6
            bar.set_postfix_str(
                f"{rate:.1f} MB/s" + (f", {p.skipped} resumed" if p.skipped else "")
            )
            bar.refresh()

        try:
            store = run_tile(src, dst, opts, progress=on_progress)
        finally:
            bar.close()
        typer.echo(f"wrote {dst}: {store.grid.rows}x{store.grid.cols} blocks, {store.k + 1} levels")
        rep = store.meta.extra.get("reprojection")
        if rep:
            from tiler.crs import crs_name

            src_crs = crs_name(store.meta.extra.get("source_crs_wkt"))
            typer.echo(
                f"reprojected from {src_crs} to {rep['crs']} ({rep['requested']}), "
                f"{rep['resolution'][0]:g} m pixels, {rep['resampling']} resampling"
            )


def register(app: typer.Typer) -> None:
    """Add ``tile`` to ``app``."""
    app.command("tile")(tile)
