"""``terrastream flythrough``: stream and render a camera path to PNG frames."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.options import LodOpt, Metric, MetricOpt, PatchOpt, PathKind, SizeOpt, parse_size


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


def register(app: typer.Typer) -> None:
    """Add ``flythrough`` to ``app``."""
    app.command("flythrough")(flythrough)
