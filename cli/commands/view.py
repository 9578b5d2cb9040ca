"""``terrastream view``: an interactive window over a store."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.options import (
    CameraOpt,
    FovOpt,
    LodOpt,
    LookAtOpt,
    Metric,
    MetricOpt,
    PatchOpt,
    PitchOpt,
    SizeOpt,
    YawOpt,
    parse_size,
)


def view(
    store: Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")],
    tau: Annotated[float, typer.Option("--tau", min=0.0, help="Starting screen error, px.")] = 1.0,
    metric: MetricOpt = Metric.qiu,
    size: SizeOpt = "1280x800",
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    patch_log2: PatchOpt = 4,
    budget_mb: Annotated[float, typer.Option("--budget-mb", help="Resident budget.")] = 512.0,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Loader threads.")] = 4,
    wireframe: Annotated[bool, typer.Option("--wireframe", help="Start in wireframe.")] = False,
    frames: Annotated[
        int | None, typer.Option("--frames", min=1, help="Run N frames without input, then exit.")
    ] = None,
    screenshot: Annotated[
        Path | None, typer.Option("--screenshot", help="With --frames: save the last frame.")
    ] = None,
    lod: LodOpt = "qiu",
) -> None:
    """Fly over a store in a window: WASD + mouse, Q/E (or C/Space) down/up, Shift faster,
    +/- tau, F or Tab wireframe, Esc releases the mouse (twice: quit).

    Needs a display (X11; on a headless machine: xvfb-run terrastream view ...).
    Example: terrastream view demo.zarr --tau 1 --size 1280x800
    """
    from render.viewer import run_viewer
    from render.views import make_camera
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        if screenshot is not None and frames is None:
            raise typer.BadParameter("--screenshot needs --frames N")
        s = open_store(store)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        res = run_viewer(
            s,
            cam,
            tau=tau,
            metric=metric.value,
            patch_log2=patch_log2,
            workers=workers,
            budget_mb=budget_mb,
            wireframe=wireframe,
            frames=frames,
            screenshot=screenshot,
            lod=lod,
        )
        st = res.last
        typer.echo(
            f"{res.frames} frames; last: {st.triangles if st else 0:,} triangles at tau "
            f"{res.tau:.3g}, {res.resident_mb:.1f} MB resident"
            + (f"; wrote {res.screenshot}" if res.screenshot else "")
        )


def register(app: typer.Typer) -> None:
    """Add ``view`` to ``app``."""
    app.command("view")(view)
