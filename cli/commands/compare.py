"""``terrastream compare``: every LOD strategy on the same fly-through."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from cli.checks import input_file, json_and_plot, open_store_arg
from cli.common import UsageError, fail_on_errors
from cli.formatters import json_text
from cli.options import (
    LODS,
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    MetricOpt,
    NodataRuleOpt,
    PatchOpt,
    PathKindOpt,
    PathOpt,
    SizeOpt,
    StorageOptionsOpt,
    StoreArg,
    TausOpt,
    check_metric_any,
    check_nodata_rule,
    frames_option,
    parse_size,
    parse_taus,
    store_location,
)

#: what ``--quick`` sets, unless given on the command line
QUICK: dict[str, Any] = {"size": "256x192", "frames": 4, "taus": "1,4"}


def compare(
    ctx: typer.Context,
    store: StoreArg,
    path: PathOpt = None,
    path_kind: PathKindOpt = "default",
    frames: Annotated[int, frames_option("Fly-through frames.")] = 8,
    taus: TausOpt = "0.5,1,2,4",
    lods: Annotated[
        str | None,
        typer.Option(
            "--lods",
            metavar="NAME,...",
            help=f"Comma-separated strategies (default: all: {LODS.placeholder}).",
        ),
    ] = None,
    size: SizeOpt = "1024x768",
    metric: MetricOpt = METRIC_DEFAULT,
    patch_log2: PatchOpt = 4,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    quick: Annotated[
        bool,
        typer.Option(
            "--quick",
            help="256x192, 4 frames, taus 1,4 (a smoke run); --size, --frames or --taus "
            "given beside it are kept.",
        ),
    ] = False,
    json_out: Annotated[
        Path | None,
        typer.Option("--json", metavar="FILE", help="One row per strategy and tau."),
    ] = None,
    plot: Annotated[
        Path | None, typer.Option("--plot", metavar="FILE", help="Pareto plot (PNG, SVG, PDF).")
    ] = None,
    storage_options: StorageOptionsOpt = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the --json and --plot files if they exist.")
    ] = False,
) -> None:
    """Compare every LOD strategy on the same fly-through: triangles, CPU/GPU ms, measured
    screen error, cracks, popping, bytes.

    Example: terrastream compare demo.zarr --taus 0.5,1,2,4 --json c.json --plot c.png
    """
    from render.pipeline import ViewOptions
    from render.strategies.compare import HEADER, plot_pareto
    from render.strategies.compare import compare as run
    from streamer.run import make_path

    with fail_on_errors():
        if quick:  # its values, except for those given on the command line
            given = {n for n in QUICK if _source(ctx, n) == "COMMANDLINE"}
            size, frames, taus = (
                v if n in given else QUICK[n]
                for n, v in (("size", size), ("frames", frames), ("taus", taus))
            )
        viewport = parse_size(size)
        values = parse_taus(taus)
        names = parse_lods(lods)
        rule = check_nodata_rule(names, nodata_rule)  # every strategy compared must take it
        check_metric_any(names, metric)  # one strategy compared at least must use it
        opts = ViewOptions(metric=metric, patch_log2=patch_log2, nodata=rule)
        input_file(path, "--path")
        inputs = [("STORE", store), ("--path", path)]
        json_and_plot(json_out, plot, overwrite, inputs)
        s = open_store_arg(store_location(store, storage_options), projected=True)
        cams = make_path(s, path_kind, frames=frames, path_file=path, viewport=viewport)
        typer.echo(HEADER)
        rows = run(s, cams, values, strategies=names, log=typer.echo, options=opts)
        if json_out:
            json_out.write_text(json_text(rows, indent=1))
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_pareto(rows, plot, title=f"{Path(store).name} {viewport[0]}x{viewport[1]}")
            typer.echo(f"wrote {plot}")


def _source(ctx: typer.Context, name: str) -> str | None:
    """Where parameter ``name`` got its value (click's ``ParameterSource`` name: typer
    vendors its own click, so the enum is compared by name)."""
    src = ctx.get_parameter_source(name)
    return None if src is None else src.name


def parse_lods(text: str | None) -> list[str] | None:
    """``qiu,jung-han`` → the names, each checked against the registry (None: all)."""
    if not text:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in LODS.names]
    if bad or not names:
        raise UsageError(
            f"unknown LOD strategy {(bad or [text])[0]!r}; choose from {', '.join(LODS.names)}",
            hint="--lods",
        )
    return names


def register(app: typer.Typer) -> None:
    """Add ``compare`` to ``app``."""
    app.command("compare")(compare)
