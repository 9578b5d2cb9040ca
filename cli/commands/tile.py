"""``terrastream tile``: a DEM into a non-redundant level store."""

from __future__ import annotations

from typing import Annotated

import typer

from cli.common import fail_on_errors


def tile(
    src: Annotated[str, typer.Argument(help="Source DEM: any raster rasterio opens.")],
    dst: Annotated[str, typer.Argument(help="Destination store (directory or fsspec URL).")],
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
    """
    from tqdm import tqdm

    from tiler.tile import TileOptions, TileProgress
    from tiler.tile import tile as run_tile

    with fail_on_errors():
        opts = TileOptions(
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


def register(app: typer.Typer) -> None:
    """Add ``tile`` to ``app``."""
    app.command("tile")(tile)
