"""``terrastream synth``: a deterministic fractal DEM."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from cli.checks import output_file
from cli.common import UsageError, fail_on_errors
from cli.options import DTYPE_DEFAULT, DTYPES, choice_option, integer, number
from cli.progress import Progress

#: ``--cell-size``'s smallest (``tiler.synth.MIN_CELL_SIZE``, not imported: the help is built
#: before any command runs, and tiler.synth imports rasterio)
MIN_CELL_SIZE = 1e-6


def synth(
    out: Annotated[Path, typer.Argument(help="Output GeoTIFF.", show_default=False)],
    size: Annotated[int, integer("--size", "Samples per side.", min=2)] = 4097,
    seed: Annotated[int, integer("--seed", "Random seed (same seed, same DEM; modulo 2^64).")] = 0,
    dtype: Annotated[str, choice_option("--dtype", DTYPES, "Sample type of the GeoTIFF.")] = (
        DTYPE_DEFAULT
    ),
    cell_size: Annotated[
        float,
        number(
            "--cell-size",
            "Metres per sample (EPSG:32633, north-west corner at 500000, 5000000): the DEM "
            "covers size x cell-size metres, at most 4e7 (the Earth's circumference).",
            min=MIN_CELL_SIZE,
            why="a millionth of a metre: finer cells cannot be told apart so far from the origin",
        ),
    ] = 30.0,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUT if it exists.")
    ] = False,
) -> None:
    """Write a deterministic fractal DEM, window by window (bounded memory, up to 2^20+1 per side).

    Progress goes to stderr (a bar on a terminal, a line every few seconds otherwise).

    Example: terrastream synth demo.tif --size 4097 --seed 1
    """
    from tiler.errors import SourceError
    from tiler.synth import MAX_SYNTH_SIZE, check_extent, synth_dem

    with fail_on_errors():
        if size <= MAX_SYNTH_SIZE:  # (a larger size is refused as such by synth_dem)
            try:
                check_extent(size, cell_size)
            except SourceError as exc:
                raise UsageError(str(exc), hint="--cell-size") from None
        output_file(out, "OUT", suffixes=(".tif", ".tiff"), overwrite=overwrite)
        bar = Progress("synth", "sample")
        t0 = time.perf_counter()

        def on_progress(done: int, total: int) -> None:
            rate = done / max(time.perf_counter() - t0, 1e-9) / 1e6
            bar.update(done, total, f"{rate:.2f} M samples/s")

        try:
            synth_dem(out, size, seed=seed, dtype=dtype, cell_size=cell_size, progress=on_progress)
        finally:
            bar.close()
        typer.echo(f"wrote {out}: {size} x {size} {dtype}, seed {seed}")


def register(app: typer.Typer) -> None:
    """Add ``synth`` to ``app``."""
    app.command("synth")(synth)
