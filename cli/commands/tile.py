"""``terrastream tile``: a DEM into a non-redundant level store."""

from __future__ import annotations

import time
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer

from cli.checks import is_local, store_destination
from cli.common import UsageError, fail_on_errors, interrupted_exit, interrupted_text
from cli.formatters import json_text
from cli.options import DstStorageOptionsOpt, integer, number, store_location
from cli.progress import Progress

#: ``--block-size`` when not given (a repair takes the store's)
DEFAULT_BLOCK_SIZE = 1025

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
    ctx: typer.Context,
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
        number(
            "--resolution",
            "Target pixel size in target CRS units (default: the source's finer side).",
            min=0.0,
            min_open=True,
        ),
    ] = None,
    block_size: Annotated[
        int | None,
        integer(
            "--block-size",
            "Block edge in samples, 2^k+1 (default 1025; with --repair: the store's).",
        ),
    ] = None,
    band: Annotated[int, integer("--band", "Band to tile (1-based).", min=1)] = 1,
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
        integer(
            "--workers",
            "Parallel workers (0 = one per CPU core): processes for large jobs (threads "
            "for up to 2 with the compiled kernels), threads for small ones and memory:// stores.",
        ),
    ] = 0,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing store.")
    ] = False,
    repair: Annotated[
        bool,
        typer.Option(
            "--repair",
            help="Recompute only the blocks `terrastream verify` finds damaged, from SRC.",
        ),
    ] = False,
    level: Annotated[int, integer("--clevel", "Compression level (blosc zstd).", min=1, max=9)] = 3,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a JSON summary instead of a line.")
    ] = False,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            metavar="SPEC",
            help="threads, processes (local pools; default: chosen by job size), dask (a local "
            "dask cluster, --workers processes) or a dask scheduler address tcp://host:port "
            "(workers read the sources and write the store themselves: both must be reachable "
            "from every worker).",
        ),
    ] = None,
    retries: Annotated[
        int, integer("--retries", "dask: retries of a failed block before the run fails.", min=0)
    ] = 2,
    storage_options: DstStorageOptionsOpt = None,
) -> None:
    """Tile a DEM into a non-redundant level store.

    Interrupted runs resume: run the same command again. Progress goes to stderr (a bar on a
    terminal, a line every few seconds otherwise).

    Example: terrastream tile N44W072.hgt n44.zarr --block-size 257

    On a dask cluster, into S3: terrastream tile dem.tif s3://bucket/dem.zarr --scheduler
    tcp://10.0.0.5:8786 (endpoint and keys from AWS_* variables or --storage-options JSON)

    Several sources form one mosaic: terrastream tile N44W072.hgt N44W073.hgt n44.zarr
    (or --from-list tiles.txt). A geographic DEM (degrees) needs --dst-crs auto to be streamed
    and rendered.
    """
    from tiler.tile import TileOptions, TileProgress, finished_generation, stored_settings
    from tiler.tile import tile as run_tile

    src, dst = _sources_and_destination(paths, from_list)
    given_resampling = _source(ctx, "resampling") == "COMMANDLINE"
    if dst_crs is None and given_resampling and not repair:  # (a repair may take the store's)
        raise typer.BadParameter(
            f"--resampling {resampling.value} applies when reprojecting; give a target CRS "
            "(--dst-crs auto|EPSG:n) or drop --resampling",
            param_hint="--resampling",
        )
    with fail_on_errors(resumable=True):
        store_destination(dst)
        if repair and is_local(dst) and not Path(dst).exists():
            raise UsageError(f"no store at {dst} to repair; tile without --repair", hint="--repair")
        target = store_location(dst, storage_options)
        before = finished_generation(target)  # (a store being replaced is not this run's)
        try:
            if repair:  # the settings the store was made with, unless given again
                made = stored_settings(target)
                block_size = made.get("block_size") if block_size is None else block_size
                precision = made.get("precision") if precision is None else precision
                if dst_crs is None and made.get("dst_crs"):  # (and its warp's settings)
                    dst_crs = made["dst_crs"]
                    if not given_resampling and made.get("resampling"):
                        resampling = Resampling(made["resampling"])
                    resolution = made.get("resolution") if resolution is None else resolution
                if dst_crs is None and given_resampling:
                    raise UsageError(
                        f"--resampling {resampling.value} applies when reprojecting, and the "
                        f"store at {dst} was not reprojected; drop --resampling",
                        hint="--resampling",
                    )
            opts = TileOptions(
                scheduler=scheduler,
                retries=retries,
                dst_crs=dst_crs,
                resampling=resampling.value,
                resolution=resolution,
                block_size=DEFAULT_BLOCK_SIZE if block_size is None else block_size,
                band=band,
                precision=precision,
                workers=workers,
                overwrite=overwrite,
                repair=repair,
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
                store = run_tile(src, target, opts, progress=on_progress)
            finally:
                bar.close()
            elapsed = time.perf_counter() - t0
            if as_json:
                typer.echo(json_text(tile_summary(dst, store, last[0] if last else None, elapsed)))
                return
            typer.echo(
                f"wrote {dst}: {store.grid.cols}x{store.grid.rows} blocks, {store.k + 1} levels"
            )
            rep = store.meta.extra.get("reprojection")
            if rep:
                from tiler.crs import crs_name

                crss = store.meta.extra.get("source_crss")  # (a mosaic of several CRSs)
                src_crs = (
                    " + ".join(crss) if crss else crs_name(store.meta.extra.get("source_crs_wkt"))
                )
                typer.echo(
                    f"reprojected from {src_crs} to {rep['crs']} ({rep['requested']}), "
                    f"{rep['resolution'][0]:g} m pixels, {rep['resampling']} resampling"
                )

        except KeyboardInterrupt:
            after = finished_generation(target)
            if after is not None and after != before:  # the interrupt came once it was done
                done = f" after {dst} was finished: the store is complete, nothing to resume"
                typer.echo(
                    interrupted_text(what=done),
                    err=True,
                )
                raise typer.Exit(interrupted_exit()) from None
            raise


def _source(ctx: typer.Context, name: str) -> str | None:
    """Where parameter ``name`` got its value (click's ``ParameterSource`` name), as
    ``compare``'s."""
    src = ctx.get_parameter_source(name)
    return None if src is None else src.name


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
