"""``terrastream stream``: fly a camera over a store, streaming what each frame needs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.common import fail_on_errors
from cli.formatters import format_summary
from cli.options import PathKind, parse_size


def stream(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    path: Annotated[
        Path | None, typer.Option("--path", help="Keyframes file (.json or .csv).")
    ] = None,
    path_kind: Annotated[PathKind, typer.Option("--path-kind", help="Built-in path.")] = (
        PathKind.default
    ),
    frames: Annotated[int, typer.Option("--frames", min=1, help="Frames to fly.")] = 600,
    fps: Annotated[float, typer.Option("--fps", min=1e-3, help="Frame rate (real time).")] = 60.0,
    speed: Annotated[
        float | None, typer.Option("--speed", help="World units/s (default 1 block edge/s).")
    ] = None,
    no_prefetch: Annotated[
        bool, typer.Option("--no-prefetch", help="Load only what frames need now.")
    ] = False,
    budget_mb: Annotated[float, typer.Option("--budget-mb", help="Resident byte budget.")] = 256.0,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Loader threads.")] = 4,
    latency_ms: Annotated[
        float, typer.Option("--latency-ms", min=0.0, help="Delay added to every store request.")
    ] = 0.0,
    tau: Annotated[float, typer.Option("--tau", min=0.0, help="Screen error threshold, px.")] = 1.0,
    metric: Annotated[str, typer.Option("--metric", help="qiu or conservative.")] = "qiu",
    size: Annotated[str, typer.Option("--size", help="Viewport WxH in pixels.")] = "1024x768",
    every: Annotated[
        int, typer.Option("--every", min=0, help="Print every N-th frame (0: auto).")
    ] = 0,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write a PNG plot.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write rows + summary.")] = None,
) -> None:
    """Fly a camera over a store in real time, streaming what each frame needs.

    Example: terrastream stream demo.zarr --frames 600 --latency-ms 20 --plot io.png
    """
    from tqdm import tqdm

    from streamer.run import make_path, plot_run, run_flythrough
    from streamer.session import SessionConfig, open_session
    from tiler.store import open_store

    with fail_on_errors():
        viewport = parse_size(size)
        s = open_store(store)
        cams = make_path(
            s,
            path_kind.value,
            frames=frames,
            fps=fps,
            speed=speed,
            path_file=path,
            viewport=viewport,
        )
        cfg = dict(fps=fps, prefetch=not no_prefetch, latency_ms=latency_ms, tau=tau, metric=metric)
        SessionConfig(budget_mb=budget_mb, workers=workers, **cfg)  # validate before starting
        every = every or max(1, frames // 20)
        header = (
            f"{'frame':>6} {'vis':>4} {'pre':>4} {'needed MB':>10} {'rt MB':>8} "
            f"{'pref MB':>8} {'I/O ms':>8} {'upd ms':>7} stall"
        )
        lines = [header]
        bar = tqdm(total=len(cams), unit="frame", desc="streaming", disable=None)

        def on_frame(i: int, st) -> None:
            bar.update(1)
            if i % every == 0 or st.stalled and i < 3:
                mb = 1 / 2**20
                lines.append(
                    f"{i:>6} {st.visible_blocks:>4} {st.prefetch_blocks:>4} "
                    f"{st.needed_bytes * mb:>10.2f} {st.realtime_bytes * mb:>8.3f} "
                    f"{st.prefetched_bytes * mb:>8.3f} {st.io_ms:>8.1f} {st.update_ms:>7.2f} "
                    f"{'yes' if st.stalled else ''}"
                )

        with open_session(s, budget_mb=budget_mb, workers=workers, **cfg) as session:
            try:
                result = run_flythrough(session, cams, on_frame=on_frame)
            finally:
                bar.close()
        typer.echo("\n".join(lines))
        typer.echo("")
        typer.echo(format_summary(result.summary))
        if json_out:
            result.to_json(json_out)
            typer.echo(f"wrote {json_out}")
        if plot:
            plot_run(result, plot)
            typer.echo(f"wrote {plot}")


def register(app: typer.Typer) -> None:
    """Add ``stream`` to ``app``."""
    app.command("stream")(stream)
