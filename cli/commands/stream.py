"""``terrastream stream``: fly a camera over a store, streaming what each frame needs."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.checks import input_file, json_and_plot, open_store_arg
from cli.common import EXIT_RUNTIME, UsageError, fail_on_errors
from cli.formatters import format_summary, json_text
from cli.options import (
    METRIC_DEFAULT,
    NODATA_DEFAULT,
    BudgetOpt,
    MetricOpt,
    NodataRuleOpt,
    PathKindOpt,
    PathOpt,
    PlotOpt,
    Registry,
    SizeOpt,
    StorageOptionsOpt,
    TauOpt,
    choice_option,
    frames_option,
    integer,
    number,
    parse_size,
    store_location,
)
from cli.progress import Progress

if TYPE_CHECKING:
    from streamer.run import RunResult

#: ``--latency-ms`` must stay below the session's wait for a frame's reads
#: (``SessionConfig.wait_timeout_s``, 30 s): at or above it no read could finish in a wait
LATENCY_MAX_MS = 30_000.0
#: the session's waits for reads (the warm-up's, frame 0's) with no injected latency, s
WAIT_BASE_S = 30.0
#: ... plus this many times ``--latency-ms``: the warm-up reads a view's levels a few at a
#: time, every request delayed (24 latencies for a 4 x 4-block store and 4 workers), so a
#: fixed 30 s timed out at 10 s per request and blamed the store's server
WAIT_LATENCIES = 100


def wait_timeout_s(latency_ms: float) -> float:
    """The session's ``wait_timeout_s`` for ``--latency-ms``: 30 s plus 100 latencies."""
    return WAIT_BASE_S + WAIT_LATENCIES * latency_ms / 1000.0


def latency_timeout(exc: BaseException, latency_ms: float, limit: float) -> UsageError | None:
    """The usage error naming ``--latency-ms`` when ``exc`` is a wait for reads that timed out
    with latency injected (the latency is the cause, not the server the message blames)."""
    from cli.common import one_line
    from streamer.errors import LoadError

    text = one_line(exc)
    blame = ": check the store's server"
    if not latency_ms or not isinstance(exc, LoadError) or blame not in text:
        return None
    return UsageError(
        f"{text.split(blame)[0]}, with {latency_ms:g} ms added to every store request: the "
        f"injected latency is the cause (the wait allows {limit:g} s, 30 s plus "
        f"{WAIT_LATENCIES} latencies); lower --latency-ms {latency_ms:g}",
        hint="--latency-ms",
    )


CULLINGS = Registry("streamer.run", "CULLINGS", "culling")


def stream(
    store: Annotated[str, typer.Argument(help="A terrastream store (path or URL).")],
    storage_options: StorageOptionsOpt = None,
    path: PathOpt = None,
    path_kind: PathKindOpt = "default",
    frames: Annotated[int, frames_option("Frames to fly.")] = 600,
    fps: Annotated[float, number("--fps", "Frame rate (real time).", min=1e-3)] = 60.0,
    speed: Annotated[
        float | None,
        number("--speed", "World units/s (default 1 block edge/s).", min=0.0, min_open=True),
    ] = None,
    no_prefetch: Annotated[
        bool, typer.Option("--no-prefetch", help="Load only what frames need now.")
    ] = False,
    budget_mb: BudgetOpt = 256.0,
    workers: Annotated[
        int, integer("--workers", "Loader threads of the session.", min=1, max=64)
    ] = 4,
    latency_ms: Annotated[
        float,
        number(
            "--latency-ms",
            "Delay added to every store request, ms (the waits for reads allow 30 s plus 100 "
            "times it).",
            min=0.0,
            max=LATENCY_MAX_MS,
            max_open=True,
            why="a read must finish within the 30 s a frame waits",
        ),
    ] = 0.0,
    tau: TauOpt = 1.0,
    metric: MetricOpt = METRIC_DEFAULT,
    nodata_rule: NodataRuleOpt = NODATA_DEFAULT,
    culling: Annotated[
        str,
        choice_option(
            "--culling",
            CULLINGS,
            "What frames stream and stalls count over: qiu (Qiu's triangle; the hull the "
            "renderer draws is counted too) or hull (the frustum hull, as flythrough).",
        ),
    ] = "qiu",
    size: SizeOpt = "1024x768",
    every: Annotated[int, integer("--every", "Print every N-th frame (0: auto).", min=0)] = 0,
    plot: PlotOpt = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", metavar="FILE", help="Write rows + summary.")
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the --json and --plot files if they exist.")
    ] = False,
) -> None:
    """Fly a camera over a store in real time, streaming what each frame needs.

    Sizes are in MiB (2^20 bytes).

    Example: terrastream stream demo.zarr --frames 600 --latency-ms 20 --plot io.png
    """
    from streamer.clip import warn_path_below_ground
    from streamer.errors import PathOutOfViewError
    from streamer.loader import THREAD_PREFIX
    from streamer.run import (
        AT_CLOSE,
        close_for_verdict,
        flight_problem,
        make_path,
        require_view,
        run_flythrough,
    )
    from streamer.session import SessionConfig, open_session

    with fail_on_errors():
        viewport = parse_size(size)
        input_file(path, "--path")
        inputs = [("STORE", store), ("--path", path)]
        json_and_plot(json_out, plot, overwrite, inputs)
        s = open_store_arg(store_location(store, storage_options), projected=True)
        cams = make_path(
            s,
            path_kind,
            frames=frames,
            fps=fps,
            speed=speed,
            path_file=path,
            viewport=viewport,
        )
        if path is not None:  # a keyframe file may dip under the terrain: say so
            warn_path_below_ground(s, cams, "a viewer flying it sees the terrain from below")
        cfg = dict(fps=fps, prefetch=not no_prefetch, latency_ms=latency_ms, tau=tau, metric=metric)
        cfg["nodata"] = nodata_rule  # the levels qiu would draw under that rule
        # Qiu's triangle misses what a steep camera sees below and behind it: under it the
        # hull the renderer draws is accounted too (stalls and holes), so the figures are true
        cfg["culling"] = culling
        cfg["account_hull"] = culling == "qiu"
        cfg["raise_on_failure"] = False  # keep flying: failures are in the frames and summary
        cfg["freeze_gc"] = True  # the command owns its process: no full collection mid-flight
        cfg["wait_timeout_s"] = wait_timeout_s(latency_ms)  # injected latency: more time
        SessionConfig(budget_mb=budget_mb, workers=workers, **cfg)  # validate before starting
        every = every or max(1, frames // 20)
        header = (
            f"{'frame':>6} {'vis':>4} {'pre':>4} {'needed MiB':>10} {'rt MiB':>8} "
            f"{'pref MiB':>8} {'I/O ms':>8} {'upd ms':>7} stall"
        )
        lines = [header]
        bar = Progress("streaming", "frame")

        def on_frame(i: int, st) -> None:
            bar.update(i + 1, len(cams))
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
            except Exception as exc:
                bar.close()
                write_partial(getattr(exc, "partial", None), exc, len(cams), json_out, plot)
                slow = latency_timeout(exc, latency_ms, cfg["wait_timeout_s"])
                if slow is not None:
                    raise slow from exc
                raise
            finally:
                bar.close()
            # reads still in flight may finish, fail or never answer: the exit status says
            unfinished, end = close_for_verdict(session)
        try:  # before any output: a flight that saw nothing is an error
            require_view(result, s)
        except PathOutOfViewError as exc:
            raise UsageError(str(exc), hint="--path") from None
        typer.echo("\n".join(lines))
        typer.echo("")
        typer.echo(format_summary(result.summary))
        hull_note(result.summary)
        unseen_note(result)
        problem = flight_problem(end, unfinished, store)
        result.summary["at_close"] = {k: end[k] for k in AT_CLOSE} | {
            "unanswered_reads": sum(n.startswith(THREAD_PREFIX) for n in unfinished),
            "problem": problem,
        }
        write_outputs(result, json_out, plot)
        if problem:
            typer.echo(f"error: the flight over {store!r} is incomplete: {problem}", err=True)
            raise typer.Exit(EXIT_RUNTIME)


def hull_note(summary: dict) -> None:
    """Under Qiu's triangle, say what the frames lacked over the frustum hull the renderer
    draws, and warn when that is more than the triangle's figures show."""
    hull_stalls, hull_holes = summary.get("stall_frames_hull"), summary.get("hole_frames_hull")
    if hull_stalls is None:
        return
    typer.echo(
        f"over the frustum hull the renderer draws: stall frames {hull_stalls}, frames with "
        f"holes {hull_holes or 0}"
    )
    if hull_stalls > summary["stall_frames"] or (hull_holes or 0) > summary["hole_frames"]:
        typer.echo(
            f"warning: {hull_stalls} of {summary['frames']} frame(s) lacked data the renderer "
            f"draws ({hull_holes or 0} with holes) where Qiu's triangle counts "
            f"{summary['stall_frames']} ({summary['hole_frames']}): the triangle misses what "
            "the camera sees beside and behind its apex; --culling hull streams what is drawn",
            err=True,
        )


def unseen_note(result: RunResult) -> None:
    """Count the frames that saw no block of the DEM (``summary.unseen_frames``) and warn when
    there are any: their stall, hole and byte figures are empty, so a path that leaves the
    DEM for most of its frames read as a flight that streamed perfectly."""
    rows = result.rows
    unseen = sum(1 for r in rows if not r["visible_blocks"])
    result.summary["unseen_frames"] = unseen
    if unseen:
        where = "Qiu's triangle" if result.summary.get("stall_set") == "triangle" else "the hull"
        typer.echo(
            f"warning: {unseen} of {len(rows)} frame(s) had no block of the DEM in view (over "
            f"{where}: the camera path leaves the DEM or looks away from it); they needed no "
            f"data and cannot stall: the figures measure streaming over the other "
            f"{len(rows) - unseen}",
            err=True,
        )


def write_partial(
    partial: RunResult | None,
    exc: BaseException,
    frames: int,
    json_out: Path | None,
    plot: Path | None,
) -> None:
    """A flight stopped by ``exc``: write its ``--json``/``--plot`` for the frames flown (the
    summary says where and why it stopped) before the error is reported."""
    from cli.common import one_line

    if partial is None or not partial.rows or not (json_out or plot):
        return
    partial.summary["stopped"] = {
        "after_frames": len(partial.rows),
        "of_frames": frames,
        "error": one_line(exc),
    }
    write_outputs(partial, json_out, plot, f" (the {len(partial.rows)} of {frames} frames flown)")


def write_outputs(
    result: RunResult, json_out: Path | None, plot: Path | None, what: str = ""
) -> None:
    """Write ``--json`` and ``--plot`` of a flight's ``result``, saying so (``what`` added)."""
    from streamer.run import plot_run

    if json_out:
        rows = {"frames": result.rows, "summary": result.summary}  # (RunResult.to_json's)
        json_out.write_text(json_text(rows, indent=1))
        typer.echo(f"wrote {json_out}{what}")
    if plot:
        plot_run(result, plot)
        typer.echo(f"wrote {plot}{what}")


def register(app: typer.Typer) -> None:
    """Add ``stream`` to ``app``."""
    app.command("stream")(stream)
