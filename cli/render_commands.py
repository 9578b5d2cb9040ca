"""The renderer's commands: ``render``, ``tradeoff``, ``flythrough``, ``view`` (wiring only)."""

from __future__ import annotations

import json
from dataclasses import asdict
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.main import PathKind, app, parse_size


class Metric(StrEnum):
    """Screen-error metrics (streamer.lod.METRICS)."""

    qiu = "qiu"
    conservative = "conservative"


CameraOpt = Annotated[
    str | None, typer.Option("--camera", help="Eye position x,y,z (world units).")
]
LookAtOpt = Annotated[str | None, typer.Option("--look-at", help="Target point x,y,z.")]
YawOpt = Annotated[float | None, typer.Option("--yaw", help="Degrees clockwise from north.")]
PitchOpt = Annotated[float | None, typer.Option("--pitch", help="Degrees above the horizon.")]
FovOpt = Annotated[float, typer.Option("--fov", min=1.0, max=170.0, help="Vertical FOV, deg.")]
SizeOpt = Annotated[str, typer.Option("--size", help="Viewport WxH in pixels.")]
MetricOpt = Annotated[Metric, typer.Option("--metric", help="Screen-error metric.")]
LodOpt = Annotated[
    str,
    typer.Option(
        "--lod", help="LOD strategy: qiu (default) or chunk-tessellation (render.strategies)."
    ),
]
PatchOpt = Annotated[
    int, typer.Option("--patch-log2", min=0, max=7, help="Patch cells per side, log2.")
]


@app.command()
def render(
    store: Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output PNG.")] = Path("view.png"),
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    size: SizeOpt = "1024x768",
    tau: Annotated[float, typer.Option("--tau", min=0.0, help="Screen error, px.")] = 1.0,
    metric: MetricOpt = Metric.qiu,
    patch_log2: PatchOpt = 4,
    wireframe: Annotated[bool, typer.Option("--wireframe", help="Overlay edges.")] = False,
    lod_colour: Annotated[bool, typer.Option("--lod-colour", help="Tint by level.")] = False,
    lod: LodOpt = "qiu",
) -> None:
    """Render one view of a store to a PNG (default: an oblique overview of the whole DEM).

    Example: terrastream render demo.zarr --camera 500000,4990000,3000 --look-at
    505000,4995000,500 --tau 1 -o view.png
    """
    from PIL import Image

    from render.pipeline import render_view
    from render.views import make_camera
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        s = open_store(store)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        img, st = render_view(
            s,
            cam,
            tau=tau,
            metric=metric.value,
            patch_log2=patch_log2,
            wireframe=wireframe,
            lod_colour=lod_colour,
            lod=lod,
        )
        Image.fromarray(img).save(out)
        typer.echo(
            f"wrote {out}: {st.triangles:,} triangles in {st.patches} patches (levels "
            f"{st.min_level}..{st.max_level}), selection {st.selection_ms:.2f} ms, GPU "
            f"{st.frame_ms:.1f} ms, {st.gpu_bytes / 2**20:.1f} MB of heights on the GPU"
            + (f", {st.clamped} nodes clamped to resident levels" if st.clamped else "")
        )


def _taus(text: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        vals = []
    if not vals or any(not v >= 0 for v in vals):
        raise typer.BadParameter(
            f"expected comma-separated taus >= 0 such as 0.5,1,2, got {text!r}"
        )
    return vals


@app.command()
def tradeoff(
    store: Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")],
    camera: CameraOpt = None,
    look_at: LookAtOpt = None,
    yaw: YawOpt = None,
    pitch: PitchOpt = None,
    fov: FovOpt = 45.0,
    size: SizeOpt = "1024x768",
    taus: Annotated[str, typer.Option("--taus", help="Comma-separated taus, px.")] = "0.5,1,2,4,8",
    metric: MetricOpt = Metric.qiu,
    patch_log2: PatchOpt = 4,
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Timed draws per tau.")] = 3,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write one row per tau.")] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write a PNG plot.")] = None,
    lod: LodOpt = "qiu",
) -> None:
    """Measure what tau costs and buys against the full-resolution render of the same view.

    Example: terrastream tradeoff demo.zarr --taus 0.5,1,2,4,8 --json t.json --plot t.png
    """
    from render.pipeline import TABLE_HEADER, plot_tradeoff
    from render.pipeline import tradeoff as run
    from render.views import make_camera
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        values = _taus(taus)
        s = open_store(store)
        cam = make_camera(
            s, viewport, position=camera, look_at=look_at, yaw=yaw, pitch=pitch, fov=fov
        )
        typer.echo(TABLE_HEADER)
        rows = run(
            s,
            cam,
            values,
            metric=metric.value,
            patch_log2=patch_log2,
            repeats=repeats,
            log=typer.echo,
            lod=lod,
        )
        if rows:
            typer.echo(
                f"reference (full resolution): {rows[0].reference_triangles:,} triangles, "
                f"{rows[0].reference_frame_ms:.1f} ms GPU"
            )
        if json_out:
            json_out.write_text(json.dumps([asdict(r) for r in rows], indent=1))
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_tradeoff(rows, plot, title=f"{Path(store).name} {viewport[0]}x{viewport[1]}")
            typer.echo(f"wrote {plot}")


@app.command()
def flythrough(
    store: Annotated[str, typer.Argument(help="Store (directory or fsspec URL).")],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")] = Path("frames"),
    path: Annotated[Path | None, typer.Option("--path", help="Keyframe file.")] = None,
    path_kind: Annotated[PathKind, typer.Option("--path-kind", help="Built-in path.")] = (
        PathKind.default
    ),
    frames: Annotated[int, typer.Option("--frames", min=1, help="Frames to render.")] = 120,
    fps: Annotated[float, typer.Option("--fps", min=1e-3, help="Path frame rate.")] = 30.0,
    tau: Annotated[float, typer.Option("--tau", min=0.0, help="Screen error, px.")] = 1.0,
    metric: MetricOpt = Metric.qiu,
    size: SizeOpt = "1024x768",
    patch_log2: PatchOpt = 4,
    budget_mb: Annotated[float, typer.Option("--budget-mb", help="Resident budget.")] = 256.0,
    workers: Annotated[int, typer.Option("--workers", min=0, help="Loader threads.")] = 2,
    every: Annotated[int, typer.Option("--every", min=0, help="Save every N-th PNG.")] = 1,
    lod: LodOpt = "qiu",
) -> None:
    """Stream and render a camera path: PNG frames, frames.csv and a summary.

    Example: terrastream flythrough demo.zarr --frames 120 --tau 1 --out frames/
    """
    from render.pipeline import flythrough as run
    from streamer.run import make_path
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        s = open_store(store)
        cams = make_path(
            s, path_kind.value, frames=frames, fps=fps, path_file=path, viewport=viewport
        )
        every_line = max(1, frames // 10)
        typer.echo(f"{'frame':>6} {'triangles':>10} {'sel ms':>7} {'GPU ms':>7} {'MB in':>7} stall")

        def on_frame(r) -> None:
            if r.frame % every_line == 0:
                typer.echo(
                    f"{r.frame:>6} {r.triangles:>10,} {r.selection_ms:>7.2f} {r.gpu_ms:>7.1f} "
                    f"{r.loaded_mb:>7.2f} {'yes' if r.stalled else ''}"
                )

        _, summary = run(
            s,
            cams,
            out,
            tau=tau,
            metric=metric.value,
            patch_log2=patch_log2,
            workers=workers,
            budget_mb=budget_mb,
            fps=fps,
            save_every=every,
            on_frame=on_frame,
            lod=lod,
        )
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
        typer.echo(
            f"{summary['frames']} frames: mean {summary['mean_triangles']:,.0f} triangles, "
            f"selection {summary['mean_selection_ms']:.2f} ms (max "
            f"{summary['max_selection_ms']:.2f}), GPU {summary['mean_gpu_ms']:.1f} ms, "
            f"{summary['stall_frames']} stalled, loaded {summary['loaded_mb']:.1f} MB; "
            f"wrote {out}/frames.csv"
        )


@app.command()
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


@app.command()
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
        values = _taus(taus)
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
