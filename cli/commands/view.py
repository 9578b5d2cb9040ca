"""``terrastream view``: an interactive window over a store."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.checks import image_suffixes, open_store_arg, output_file
from cli.commands.render import image_format
from cli.common import EXIT_RUNTIME, UsageError, fail_on_errors
from cli.options import (
    LOD_DEFAULT,
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    BudgetOpt,
    CameraOpt,
    FovOpt,
    LodOpt,
    LookAtOpt,
    MetricOpt,
    NodataRuleOpt,
    PatchOpt,
    PitchOpt,
    SizeOpt,
    StorageOptionsOpt,
    StoreArg,
    TauOpt,
    YawOpt,
    check_metric,
    check_nodata_rule,
    frames_option,
    integer,
    parse_size,
    store_location,
)


def view(
    store: StoreArg,
    tau: TauOpt = 1.0,
    metric: MetricOpt = METRIC_DEFAULT,
    size: SizeOpt = "1280x800",
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    patch_log2: PatchOpt = 4,
    budget_mb: BudgetOpt = 512.0,
    workers: Annotated[
        int, integer("--workers", "Loader threads of the streaming session.", min=1)
    ] = 4,
    wireframe: Annotated[bool, typer.Option("--wireframe", help="Start in wireframe.")] = False,
    frames: Annotated[int | None, frames_option("Run N frames without input, then exit.")] = None,
    screenshot: Annotated[
        Path | None,
        typer.Option(
            "--screenshot", metavar="FILE", help="With --frames: save the last frame (an image)."
        ),
    ] = None,
    lod: LodOpt = LOD_DEFAULT,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    storage_options: StorageOptionsOpt = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the --screenshot file if it exists.")
    ] = False,
) -> None:
    """Fly over a store in a window: WASD + mouse, Q/E (or C/Space) down/up, Shift faster,
    +/- tau, F or Tab wireframe, Esc releases the mouse (twice: quit).

    Needs a display (X11; on a headless machine: xvfb-run terrastream view ...).
    Example: terrastream view demo.zarr --tau 1 --size 1280x800
    """
    from render.pipeline import ViewOptions
    from render.viewer import run_viewer
    from render.views import make_camera

    with fail_on_errors():
        viewport = parse_size(size)
        opts = ViewOptions(
            lod=lod, tau=tau, metric=check_metric(lod, metric), patch_log2=patch_log2,
            wireframe=wireframe,
            nodata=check_nodata_rule([lod], nodata_rule),
        )  # fmt: skip
        if screenshot is not None and frames is None:
            raise UsageError("--screenshot needs --frames N")
        output_file(
            screenshot,
            "--screenshot",
            suffixes=image_suffixes() if screenshot else None,
            overwrite=overwrite,
            inputs=[("STORE", store)],
        )
        if screenshot is not None:
            image_format(screenshot, "--screenshot")  # (an .xbm: refused before flying)
        s = open_store_arg(store_location(store, storage_options), projected=True)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        res = run_viewer(
            s,
            cam,
            workers=workers,
            budget_mb=budget_mb,
            frames=frames,
            screenshot=screenshot,
            options=opts,
        )
        st = res.last
        blank = frames is not None and (st is None or st.drawn_px == 0)  # a picture of sky
        typer.echo(
            f"{res.frames} frames; last: {st.triangles if st else 0:,} triangles at tau "
            f"{res.tau:.3g}, {res.resident_mb:.1f} MiB resident"
            + (f"; wrote {res.screenshot}" if res.screenshot else "")
        )
        if frames is not None and res.ground and not blank:  # seen from below the ground
            shot = f"the screenshot {str(res.screenshot)!r}" if res.screenshot else "the last frame"
            typer.echo(f"warning: {shot} was taken where {res.ground}", err=True)
        unseen = blank and res.visible_blocks == 0  # it looked away: that is the first error
        if res.problem and not unseen:  # drawn without data it needed: not a view of the store
            typer.echo(
                f"error: the view of {store!r} is incomplete: {res.problem}"
                + ("; the screenshot was not kept" if screenshot is not None else ""),
                err=True,
            )
            raise typer.Exit(EXIT_RUNTIME)
        if blank:  # never a screenshot of sky with exit 0 (as `render`)
            tris = st.triangles if st else 0
            why = res.ground or (
                "the camera sees none of the DEM"
                if unseen
                else "none of its levels could be loaded"
                if tris == 0
                else "its triangles are all smaller than a pixel or outside the view"
            )
            raise UsageError(
                f"the last of the {res.frames} frame(s) of {store!r} drew no terrain pixel "
                f"({tris:,} triangles): {why}; point the camera at the terrain (--camera, "
                "--look-at, --pitch)"
                + ("; the screenshot was not kept" if screenshot is not None else ""),
                hint="--camera",
            )


def register(app: typer.Typer) -> None:
    """Add ``view`` to ``app``."""
    app.command("view")(view)
