"""The ``terrastream`` command: wires the tiler, streamer and renderer; no logic of its own."""

from __future__ import annotations

import json
import logging
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors, human_bytes, setup_logging

app = typer.Typer(
    name="terrastream",
    help="Out-of-core terrain: tile DEMs into zarr stores, stream and render them.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="More logging.")] = 0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only errors.")] = False,
) -> None:
    setup_logging(verbose, quiet)


@app.command()
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


@app.command()
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


def format_info(d: dict) -> str:
    """The human-readable ``info`` table."""
    lines = [
        f"store          {d['url']}",
        f"format         v{d['format_version']}, written by terrastream {d['tool_version']}",
        f"source         {d['source']} ({d['checksum']})",
        f"samples        {d['height']} x {d['width']} {d['dtype']}"
        + (f", quantised to {d['precision']} m" if d["precision"] else ", lossless"),
        f"blocks         {d['block_rows']} x {d['block_cols']} of {d['block_size']}^2 "
        f"({d['blocks_with_terrain']} with terrain, {d['blocks_with_nodata']} with nodata)",
        f"levels         {d['levels']} (encoding {d['encoding']}, {d['compressor']})",
        f"nodata         {d['nodata']}",
        f"crs            {d['crs']}",
        f"extent         x {d['extent'][0]:.3f} .. {d['extent'][2]:.3f}, "
        f"y {d['extent'][1]:.3f} .. {d['extent'][3]:.3f}",
        f"values         {d['value_range'][0]:g} .. {d['value_range'][1]:g}"
        + (f" {d['vertical_units']}" if d["vertical_units"] else ""),
        "",
        "level  values/block      stored     share",
    ]
    total = d["bytes"]["total"]
    for row in d["bytes_per_level"]:
        lines.append(
            f"{row['level']:>5}  {row['values_per_block']:>12}  {human_bytes(row['bytes']):>10}"
            f"  {100 * row['bytes'] / max(total, 1):6.2f} %"
        )
    b = d["bytes"]
    lines += [
        "",
        f"levels {human_bytes(b['levels'])}, errors {human_bytes(b['errors'])}, "
        f"mask {human_bytes(b['mask'])}, index {human_bytes(b['index'])}, "
        f"metadata {human_bytes(b['metadata'])}",
        f"total {human_bytes(total)} = {d['ratio_to_raw']:.3f} x raw "
        f"({human_bytes(d['raw_bytes'])})",
    ]
    return "\n".join(lines)


@app.command()
def synth(
    out: Annotated[Path, typer.Argument(help="Output GeoTIFF.")],
    size: Annotated[int, typer.Option("--size", help="Samples per side.")] = 4097,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (same seed, same DEM).")] = 0,
    dtype: Annotated[str, typer.Option("--dtype", help="int16 or float32.")] = "int16",
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUT if it exists.")
    ] = False,
) -> None:
    """Write a deterministic fractal DEM, window by window (any size, bounded memory).

    Example: terrastream synth demo.tif --size 4097 --seed 1
    """
    from tqdm import tqdm

    from tiler.synth import synth_dem

    with fail_on_errors():
        if out.exists() and not overwrite:
            raise typer.BadParameter(
                f"{out} exists; pass --overwrite to replace it", param_hint="OUT"
            )
        bar = tqdm(total=size * size, unit="sample", unit_scale=True, desc="synth", disable=None)

        def on_progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        try:
            synth_dem(out, size, seed=seed, dtype=dtype, progress=on_progress)
        finally:
            bar.close()
        typer.echo(f"wrote {out}: {size} x {size} {dtype}, seed {seed}")


@app.command()
def export(
    store: Annotated[str, typer.Argument(help="A terrastream store.")],
    out: Annotated[Path, typer.Argument(help="Output GeoTIFF.")],
    level: Annotated[
        int | None, typer.Option("--level", help="Level to export (default: the finest).")
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUT if it exists.")
    ] = False,
) -> None:
    """Rebuild a GeoTIFF of the whole DEM from a store (bit-identical when lossless).

    Example: terrastream export n44.zarr n44.tif --level 8
    """
    from tiler.export import export_geotiff
    from tiler.store import open_store

    with fail_on_errors():
        if out.exists() and not overwrite:
            raise typer.BadParameter(
                f"{out} exists; pass --overwrite to replace it", param_hint="OUT"
            )
        s = open_store(store)
        export_geotiff(s, out, level)
        typer.echo(f"wrote {out} (level {s.k if level is None else level} of {s.k})")


class PathKind(StrEnum):
    """Built-in fly-through paths."""

    default = "default"
    line = "line"
    circle = "circle"
    canyon = "canyon"
    teleports = "teleports"


@app.command()
def stream(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    path: Annotated[
        Path | None, typer.Option("--path", help="Keyframes file (.json or .csv).")
    ] = None,
    path_kind: Annotated[PathKind, typer.Option("--path-kind", help="Built-in path.")] = (
        PathKind.default
    ),
    frames: Annotated[int, typer.Option("--frames", min=1, help="Frames to fly.")] = 600,
    fps: Annotated[float, typer.Option("--fps", min=1e-3, help="Frame rate (real time).")] = 60.0,
    speed: Annotated[
        float | None, typer.Option("--speed", help="World units/s (default 1 block edge/s).")
    ] = None,
    no_prefetch: Annotated[
        bool, typer.Option("--no-prefetch", help="Load only what frames need now.")
    ] = False,
    budget_mb: Annotated[float, typer.Option("--budget-mb", help="Resident byte budget.")] = 256.0,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Loader threads.")] = 4,
    latency_ms: Annotated[
        float, typer.Option("--latency-ms", min=0.0, help="Delay added to every store request.")
    ] = 0.0,
    tau: Annotated[float, typer.Option("--tau", min=0.0, help="Screen error threshold, px.")] = 1.0,
    metric: Annotated[str, typer.Option("--metric", help="qiu or conservative.")] = "qiu",
    size: Annotated[str, typer.Option("--size", help="Viewport WxH in pixels.")] = "1024x768",
    every: Annotated[
        int, typer.Option("--every", min=0, help="Print every N-th frame (0: auto).")
    ] = 0,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write a PNG plot.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write rows + summary.")] = None,
) -> None:
    """Fly a camera over a store in real time, streaming what each frame needs.

    Example: terrastream stream demo.zarr --frames 600 --latency-ms 20 --plot io.png
    """
    from tqdm import tqdm

    from streamer.run import make_path, plot_run, run_flythrough
    from streamer.session import SessionConfig, open_session
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        s = open_store(store)
        cams = make_path(
            s,
            path_kind.value,
            frames=frames,
            fps=fps,
            speed=speed,
            path_file=path,
            viewport=viewport,
        )
        cfg = dict(fps=fps, prefetch=not no_prefetch, latency_ms=latency_ms, tau=tau, metric=metric)
        SessionConfig(budget_mb=budget_mb, workers=workers, **cfg)  # validate before starting
        every = every or max(1, frames // 20)
        header = (
            f"{'frame':>6} {'vis':>4} {'pre':>4} {'needed MB':>10} {'rt MB':>8} "
            f"{'pref MB':>8} {'I/O ms':>8} {'upd ms':>7} stall"
        )
        lines = [header]
        bar = tqdm(total=len(cams), unit="frame", desc="streaming", disable=None)

        def on_frame(i: int, st) -> None:
            bar.update(1)
            if i % every == 0 or st.stalled and i < 3:
                mb = 1 / 2**20
                lines.append(
                    f"{i:>6} {st.visible_blocks:>4} {st.prefetch_blocks:>4} "
                    f"{st.needed_bytes * mb:>10.2f} {st.realtime_bytes * mb:>8.3f} "
                    f"{st.prefetched_bytes * mb:>8.3f} {st.io_ms:>8.1f} {st.update_ms:>7.2f} "
                    f"{'yes' if st.stalled else ''}"
                )

        with open_session(s, budget_mb=budget_mb, workers=workers, **cfg) as session:
            try:
                result = run_flythrough(session, cams, on_frame=on_frame)
            finally:
                bar.close()
        typer.echo("\n".join(lines))
        typer.echo("")
        typer.echo(format_summary(result.summary))
        if json_out:
            result.to_json(json_out)
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_run(result, plot)
            typer.echo(f"wrote {plot}")


def format_summary(d: dict) -> str:
    """The stream summary block."""
    mb = 1 / 2**20
    needed = max(d["needed_bytes"], 1)
    used = max(d["used_bytes"], 1)
    return "\n".join(
        [
            f"frames {d['frames']}, stall frames {d['stall_frames']}, io errors {d['io_errors']}",
            f"warm-up before frame 0: {d['warmup_bytes'] * mb:.2f} MB in {d['warmup_ms']:.0f} ms",
            f"needed {d['needed_bytes'] * mb:.1f} MB over all frames; real-time loaded "
            f"{d['realtime_bytes'] * mb:.3f} MB "
            f"({100 * d['realtime_bytes_after_first_frame'] / needed:.3f} % of needed after "
            "frame 1)",
            f"loaded {d['loaded_bytes'] * mb:.2f} MB, used {d['used_bytes'] * mb:.2f} MB "
            f"(loaded/used {d['loaded_bytes'] / used:.2f}), wasted {d['wasted_bytes'] * mb:.2f} MB",
            f"peak resident {d['peak_resident_bytes'] * mb:.2f} MB of a "
            f"{d['budget_bytes'] * mb:.0f} MB budget; max update {d['max_update_ms']:.2f} ms "
            f"(CPU {d['max_update_cpu_ms']:.2f} ms)",
        ]
    )


def parse_size(text: str) -> tuple[int, int]:
    """``1024x768`` → ``(1024, 768)``; a clear error otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT such as 1024x768, got {text!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise typer.BadParameter(f"viewport {w}x{h} is outside 1..16384 pixels per side")
    return w, h


def _register_optional_commands() -> None:
    """Commands that live in their own modules (the renderer's), registered on ``app``."""
    import importlib

    for name in ("cli.render_commands",):
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise


_register_optional_commands()


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
    # ``python -m cli.main``: run the imported module's app, where the optional command
    # modules registered themselves (this file also runs as ``__main__``, a second copy).
    from cli.main import main as _entry

    _entry()
