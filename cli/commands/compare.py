"""``terrastream compare``: every LOD strategy on the same fly-through."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.options import Metric, MetricOpt, PatchOpt, PathKind, SizeOpt, parse_size, parse_taus


def compare(
    store: Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")],
    path: Annotated[Path | None, typer.Option("--path", help="Keyframe file.")] = None,
    path_kind: Annotated[PathKind, typer.Option("--path-kind", help="Built-in path.")] = (
        PathKind.default
    ),
    frames: Annotated[int, typer.Option("--frames", min=1, help="Fly-through frames.")] = 8,
    taus: Annotated[str, typer.Option("--taus", help="Comma-separated taus, px.")] = "0.5,1,2,4",
    lods: Annotated[
        str | None, typer.Option("--lods", help="Comma-separated strategies (default: all).")
    ] = None,
    size: SizeOpt = "1024x768",
    metric: MetricOpt = Metric.qiu,
    patch_log2: PatchOpt = 4,
    quick: Annotated[
        bool, typer.Option("--quick", help="256x192, 4 frames, taus 1,4 (a smoke run).")
    ] = False,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="One row per strategy and tau.")
    ] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="Pareto plot PNG.")] = None,
) -> None:
    """Compare every LOD strategy on the same fly-through: triangles, CPU/GPU ms, measured
    screen error, cracks, popping, bytes.

    Example: terrastream compare demo.zarr --taus 0.5,1,2,4 --json c.json --plot c.png
    """
    from render.strategies import check_name
    from render.strategies.compare import HEADER, plot_pareto
    from render.strategies.compare import compare as run
    from streamer.run import make_path
    from tiler.store import open_store

    with fail_on_errors():
        if quick:
            size, frames, taus = "256x192", 4, "1,4"
        viewport = parse_size(size)
        values = parse_taus(taus)
        names = [check_name(n.strip()) for n in lods.split(",")] if lods else None
        s = open_store(store)
        cams = make_path(s, path_kind.value, frames=frames, path_file=path, viewport=viewport)
        typer.echo(HEADER)
        rows = run(
            s,
            cams,
            values,
            strategies=names,
            metric=metric.value,
            patch_log2=patch_log2,
            log=typer.echo,
        )
        if json_out:
            json_out.write_text(json.dumps(rows, indent=1))
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_pareto(rows, plot, title=f"{Path(store).name} {viewport[0]}x{viewport[1]}")
            typer.echo(f"wrote {plot}")


def register(app: typer.Typer) -> None:
    """Add ``compare`` to ``app``."""
    app.command("compare")(compare)
