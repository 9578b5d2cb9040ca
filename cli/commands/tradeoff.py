"""``terrastream tradeoff``: what tau costs and buys for one view."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Annotated

import typer

from cli.checks import json_and_plot, open_store_arg
from cli.common import fail_on_errors
from cli.formatters import json_text
from cli.options import (
    LOD_DEFAULT,
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    CameraOpt,
    FovOpt,
    LodOpt,
    LookAtOpt,
    MetricOpt,
    NodataRuleOpt,
    PatchOpt,
    PitchOpt,
    PlotOpt,
    SizeOpt,
    StorageOptionsOpt,
    StoreArg,
    TausOpt,
    YawOpt,
    check_metric,
    check_nodata_rule,
    integer,
    parse_size,
    parse_taus,
    store_location,
)


def tradeoff(
    store: StoreArg,
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    size: SizeOpt = "1024x768",
    taus: TausOpt = "0.5,1,2,4,8",
    metric: MetricOpt = METRIC_DEFAULT,
    patch_log2: PatchOpt = 4,
    repeats: Annotated[int, integer("--repeats", "Timed draws per tau.", min=1)] = 3,
    json_out: Annotated[
        Path | None, typer.Option("--json", metavar="FILE", help="Write one row per tau.")
    ] = None,
    plot: PlotOpt = None,
    lod: LodOpt = LOD_DEFAULT,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    storage_options: StorageOptionsOpt = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the --json and --plot files if they exist.")
    ] = False,
) -> None:
    """Measure what tau costs and buys against the full-resolution render of the same view.

    Example: terrastream tradeoff demo.zarr --taus 0.5,1,2,4,8 --json t.json --plot t.png
    """
    from render.pipeline import TABLE_HEADER, ViewOptions, plot_tradeoff
    from render.pipeline import tradeoff as run
    from render.views import make_camera

    with fail_on_errors():
        viewport = parse_size(size)
        values = parse_taus(taus)
        rule = check_nodata_rule([lod], nodata_rule)
        check_metric(lod, metric)
        opts = ViewOptions(lod=lod, metric=metric, patch_log2=patch_log2, nodata=rule)
        inputs = [("STORE", store)]
        json_and_plot(json_out, plot, overwrite, inputs)
        s = open_store_arg(store_location(store, storage_options), projected=True)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        shown: list[str] = []

        def log(line: str) -> None:  # the header with the first row (not before an error)
            if not shown:
                shown.append(TABLE_HEADER)
                typer.echo(TABLE_HEADER)
            typer.echo(line)

        rows = run(s, cam, values, repeats=repeats, log=log, options=opts)
        if rows:
            typer.echo(
                f"reference (full resolution): {rows[0].reference_triangles:,} triangles, "
                f"{rows[0].reference_frame_ms:.1f} ms GPU"
            )
        if json_out:
            json_out.write_text(json_text([asdict(r) for r in rows], indent=1))
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_tradeoff(rows, plot, title=f"{Path(store).name} {viewport[0]}x{viewport[1]}")
            typer.echo(f"wrote {plot}")


def register(app: typer.Typer) -> None:
    """Add ``tradeoff`` to ``app``."""
    app.command("tradeoff")(tradeoff)
