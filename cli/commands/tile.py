"""``terrastream tile``: a DEM into a non-redundant level store."""

from __future__ import annotations

import json
import time
from typing import Annotated, Any

import typer

from cli.checks import store_destination
from cli.common import fail_on_errors
from cli.options import integer, number
from cli.progress import Progress


def tile(
    src: Annotated[
        str, typer.Argument(help="Source DEM: any raster rasterio opens.", show_default=False)
    ],
    dst: Annotated[str, typer.Argument(help="Destination store (directory or fsspec URL).")],
    block_size: Annotated[
        int, typer.Option("--block-size", help="Block edge in samples, 2^k+1.")
    ] = 1025,
    band: Annotated[int, typer.Option("--band", help="Band to tile (1-based).")] = 1,
    precision: Annotated[
        float | None,
        number(
            "--precision",
            "Float DEMs only: quantise to this step (max error step/2).",
            min=0.0,
            min_open=True,
        ),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            help="Parallel workers (0 = one per CPU core): processes for large jobs, threads "
            "for small ones and memory:// stores.",
        ),
    ] = 0,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing store.")
    ] = False,
    level: Annotated[int, integer("--clevel", "Compression level (blosc zstd).", min=1, max=9)] = 5,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a JSON summary instead of a line.")
    ] = False,
) -> None:
    """Tile a DEM into a non-redundant level store.

    Interrupted runs resume: run the same command again. Progress goes to stderr (a bar on a
    terminal, a line every few seconds otherwise).

    Example: terrastream tile N44W072.hgt n44.zarr --block-size 257
    """
    from tiler.tile import TileOptions, TileProgress
    from tiler.tile import tile as run_tile

    with fail_on_errors():
        store_destination(dst)
        opts = TileOptions(
            block_size=block_size,
            band=band,
            precision=precision,
            workers=workers,
            overwrite=overwrite,
            compression_level=level,
        )
        bar = Progress("tiling", "block")
        last: list[TileProgress] = []

        def on_progress(p: TileProgress) -> None:
            last[:] = [p]
            rate = p.bytes_done / max(p.elapsed_s, 1e-9) / 2**20
            bar.update(
                p.blocks_done,
                p.blocks_total,
                f"{rate:.1f} MiB/s" + (f", {p.skipped} resumed" if p.skipped else ""),
            )

        t0 = time.perf_counter()
        try:
            store = run_tile(src, dst, opts, progress=on_progress)
        finally:
            bar.close()
        elapsed = time.perf_counter() - t0
        if as_json:
            typer.echo(json.dumps(tile_summary(dst, store, last[0] if last else None, elapsed)))
            return
        typer.echo(f"wrote {dst}: {store.grid.cols}x{store.grid.rows} blocks, {store.k + 1} levels")


def tile_summary(dst: str, store: Any, p: Any, elapsed_s: float) -> dict[str, Any]:
    """The ``--json`` summary of a finished run (``p``: the last progress report or None)."""
    source_bytes = int(p.bytes_done) if p else 0
    return {
        "store": dst,
        "width": int(store.meta.width),
        "height": int(store.meta.height),
        "block_size": int(store.meta.block_size),
        "block_cols": int(store.grid.cols),
        "block_rows": int(store.grid.rows),
        "levels": int(store.k + 1),
        "blocks_total": int(p.blocks_total) if p else int(store.grid.rows * store.grid.cols),
        "blocks_resumed": int(p.skipped) if p else 0,
        "source_bytes": source_bytes,
        "elapsed_s": round(elapsed_s, 3),
        "source_MiB_per_s": round(source_bytes / 2**20 / max(elapsed_s, 1e-9), 3),
    }


def register(app: typer.Typer) -> None:
    """Add ``tile`` to ``app``."""
    app.command("tile")(tile)
