"""``terrastream synth``: a deterministic fractal DEM."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors


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


def register(app: typer.Typer) -> None:
    """Add ``synth`` to ``app``."""
    app.command("synth")(synth)
