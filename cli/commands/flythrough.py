"""``terrastream flythrough``: stream and render a camera path to PNG frames."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from streamer.camera import Camera
    from tiler.store import TerrainStore

from cli.checks import (
    input_file,
    not_an_input,
    open_store_arg,
    output_dir,
    remove_if_left_empty,
)
from cli.common import EXIT_RUNTIME, UsageError, fail_on_errors, interrupted_text, one_line
from cli.formatters import json_text
from cli.options import (
    LOD_DEFAULT,
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    BudgetOpt,
    LodOpt,
    MetricOpt,
    NodataRuleOpt,
    PatchOpt,
    PathKindOpt,
    PathOpt,
    SizeOpt,
    StorageOptionsOpt,
    StoreArg,
    TauOpt,
    check_metric,
    check_nodata_rule,
    frames_option,
    integer,
    number,
    parse_size,
    store_location,
)


def flythrough(
    store: StoreArg,
    out: Annotated[
        Path, typer.Option("--out", metavar="DIR", help="Output directory (created).")
    ] = Path("frames"),
    path: PathOpt = None,
    path_kind: PathKindOpt = "default",
    frames: Annotated[int, frames_option("Frames to render.")] = 120,
    fps: Annotated[float, number("--fps", "Path frame rate.", min=1e-3)] = 30.0,
    tau: TauOpt = 1.0,
    metric: MetricOpt = METRIC_DEFAULT,
    size: SizeOpt = "1024x768",
    patch_log2: PatchOpt = 4,
    budget_mb: BudgetOpt = 256.0,
    workers: Annotated[
        int,
        integer(
            "--workers",
            "Loader threads of the streaming session (0: load inside each frame).",
            min=0,
            max=64,
        ),
    ] = 2,
    every: Annotated[
        int,
        integer(
            "--every",
            "Save every N-th frame as a PNG (0: no PNGs; frames.csv and summary.json are "
            "written all the same).",
            min=0,
        ),
    ] = 1,
    lod: LodOpt = LOD_DEFAULT,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    storage_options: StorageOptionsOpt = None,
    render_thread_builds: Annotated[
        bool,
        typer.Option(
            "--render-thread-builds",
            help="Build each block's per-level data (geometry-splitting's quadtree texture) "
            "in the frame that needs it, as a one-shot render does; by default a level "
            "change's is built on a worker thread and frames use the previous one meanwhile.",
        ),
    ] = False,
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite",
            help="Replace the frames, frames.csv and summary.json of an earlier fly-through "
            "in --out (other files there are left).",
        ),
    ] = False,
) -> None:
    """Stream and render a camera path: PNG frames, frames.csv and a summary.

    Example: terrastream flythrough demo.zarr --frames 120 --tau 1 --out frames/
    """
    from render.flythrough import flythrough as run
    from render.pipeline import ViewOptions
    from streamer.errors import CameraError, PathOutOfViewError
    from streamer.run import make_path

    made = not out.exists()  # an --out folder made here and left empty by an error goes
    try:
        with fail_on_errors():
            viewport = parse_size(size)
            rule = check_nodata_rule([lod], nodata_rule)
            check_metric(lod, metric)
            opts = ViewOptions(lod=lod, tau=tau, metric=metric, patch_log2=patch_log2, nodata=rule)
            input_file(path, "--path")
            not_an_input(out, "--out", [("STORE", store)])
            output_dir(out, "--out")
            old = earlier_outputs(out, overwrite)  # (refused at once without --overwrite)
            for p in old:
                not_an_input(p, "--out", [("--path", path)])  # a keyframe file named frames.csv
            s = open_store_arg(store_location(store, storage_options), projected=True)
            try:
                cams = make_path(
                    s, path_kind, frames=frames, fps=fps, path_file=path, viewport=viewport
                )
            except CameraError as exc:  # (a keyframe far beyond the DEM: no far plane holds it)
                where = f"a camera of the path in {str(path)!r}" if path else "a camera"
                raise UsageError(
                    f"{where} cannot be drawn: {exc}; keep the path near the DEM", hint="--path"
                ) from None
            check_cameras_near(s, cams, path)
            for p in old:  # removed only once the store is open and the path built
                p.unlink(missing_ok=True)
            every_line = max(1, frames // 10)
            typer.echo(
                f"{'frame':>6} {'triangles':>10} {'sel ms':>7} {'GPU ms':>7} {'MiB in':>7} stall"
            )

            def on_frame(r) -> None:
                if r.frame % every_line == 0:
                    typer.echo(
                        f"{r.frame:>6} {r.triangles:>10,} {r.selection_ms:>7.2f} {r.gpu_ms:>7.1f} "
                        f"{r.loaded_mb:>7.2f} {'yes' if r.stalled else ''}"
                    )

            try:
                _, summary = run(
                    s,
                    cams,
                    out,
                    workers=workers,
                    budget_mb=budget_mb,
                    fps=fps,
                    save_every=every,
                    on_frame=on_frame,
                    options=opts,
                    background_builds=not render_thread_builds,
                )
            except PathOutOfViewError as exc:
                raise UsageError(str(exc), hint="--path") from None
            except BaseException as exc:  # (Ctrl-C included: its frames are kept the same way)
                flown = getattr(exc, "frames_flown", 0)
                if flown:  # frames.csv has them; the summary says where and why it stopped
                    stopped = {
                        "after_frames": flown,
                        "of_frames": len(cams),
                        "error": interrupted_text()
                        if isinstance(exc, KeyboardInterrupt)
                        else one_line(exc),
                    }
                    (out / "summary.json").write_text(json_text({"stopped": stopped}, indent=1))
                    typer.echo(
                        f"wrote {out}/frames.csv and summary.json ({flown} of {len(cams)} frames)"
                    )
                raise
            (out / "summary.json").write_text(json_text(summary, indent=1))
            typer.echo(
                f"{summary['frames']} frames: mean {summary['mean_triangles']:,.0f} triangles, "
                f"selection {summary['mean_selection_ms']:.2f} ms (max "
                f"{summary['max_selection_ms']:.2f}; builds max {summary['max_build_ms']:.2f}), "
                f"GPU {summary['mean_gpu_ms']:.1f} ms, "
                f"{summary['stall_frames']} stalled, loaded {summary['loaded_mb']:.1f} MiB"
                + (
                    f" (+{summary['loaded_after_frames_mb']:.1f} read ahead after the last frame)"
                    if summary["loaded_after_frames_mb"] >= 0.05
                    else ""
                )
                + "; "
                f"wrote {out}/frames.csv"
            )
            if summary["empty_frames"]:
                n, unseen = summary["empty_frames"], summary["unseen_frames"]
                tiny = summary["pixelless_frames"]
                why = "the camera sees none of the DEM there"
                if unseen < n:
                    parts = [f"{unseen} saw none of the DEM"]
                    if n - unseen - tiny:
                        parts.append(
                            f"{n - unseen - tiny} had none of its levels loaded yet (stalled)"
                        )
                    if tiny:
                        parts.append(
                            f"{tiny} drew triangles covering no pixel (too far, or terrain too "
                            "sparse to draw)"
                        )
                    why = ", ".join(parts)
                typer.echo(
                    f"warning: {n} of {summary['frames']} frames drew no terrain (the first: frame "
                    f"{summary['first_empty_frame']}): {why}",
                    err=True,
                )
            if summary["problem"]:  # the frames and summary are written; the run is incomplete
                typer.echo(
                    f"error: the fly-through over {store!r} is incomplete: {summary['problem']}",
                    err=True,
                )
                raise typer.Exit(EXIT_RUNTIME)
    finally:
        remove_if_left_empty(out, made)


def check_cameras_near(store: TerrainStore, cams: list[Camera], path: Path | None) -> None:
    """Refuse (a usage error naming --path, before any frame is flown) a path with a camera
    more than 2^31 cells from the DEM's origin, beyond the renderer's 32-bit cell index (it
    stopped the flight at that frame, exit 1)."""
    from render.views import CAMERA_CELL_LIMIT, camera_cells

    g = store.grid
    for i, c in enumerate(cams):
        x, y = float(c.position[0]), float(c.position[1])
        if camera_cells(g, x, y) > CAMERA_CELL_LIMIT - 2:
            far = CAMERA_CELL_LIMIT * min(abs(g.dx), abs(g.dy))
            raise UsageError(
                f"frame {i} of the path"
                + (f" in {str(path)!r}" if path else "")
                + f" puts the camera at x {x:.6g}, y {y:.6g}, more than 2^31 cells from the "
                "DEM's origin, beyond the renderer's 32-bit cell index; keep the path within "
                f"{far:.3g} m of the DEM",
                hint="--path",
            )


def earlier_outputs(out: Path, overwrite: bool) -> list[Path]:
    """Refuse an ``out`` holding an earlier fly-through's files (its PNGs would stay beside
    the new ones, unlike them), or, when ``overwrite``, return those files: the caller removes
    them once the store is open and the path built (a typo in STORE or --path left the
    earlier fly-through deleted, and nothing new)."""
    old = sorted(out.glob("frame_*.png")) + [
        p for p in (out / "frames.csv", out / "summary.json") if p.exists()
    ]
    if not old:
        return []
    if not overwrite:
        pngs = sum(p.suffix == ".png" for p in old)
        raise UsageError(
            f"{str(out)!r} holds an earlier fly-through ({pngs} frame PNG(s)"
            + (", frames.csv" if (out / "frames.csv").exists() else "")
            + "); pass --overwrite to replace it, or give another --out",
            hint="--out",
        )
    return old


def register(app: typer.Typer) -> None:
    """Add ``flythrough`` to ``app``."""
    app.command("flythrough")(flythrough)
