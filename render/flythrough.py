"""Fly-throughs: stream and render a camera path to PNG frames, ``frames.csv`` and a summary.

Each frame is streamed through a session (``culling="hull"``: the blocks the renderer draws)
and drawn with the resident levels, as in real time: frames wait for their data until the first
one that sees the DEM, later ones draw what has arrived (``stalled`` when a level is missing).
A path none of whose frames draws terrain is an error, not a folder of blank frames; a flight
whose reads failed or went unanswered says so in ``summary["problem"]`` (the CLI exits 1)."""

from __future__ import annotations

import csv
import io
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from render.errors import EmptyViewError, RenderError
from render.pipeline import ViewOptions, session_patch_log2
from render.renderer import RenderConfig, TerrainRenderer
from render.step import frame_step
from render.strategies import DEFAULT, get_strategy, stream_metric
from streamer.camera import Camera
from streamer.clip import warn_path_below_ground
from streamer.run import close_for_verdict, flight_problem, frames_summary, out_of_view
from streamer.session import open_session
from tiler.atomic import write_atomic
from tiler.store import TerrainStore

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FlyRow:
    """One fly-through frame (a CSV row)."""

    frame: int
    triangles: int
    patches: int
    selection_ms: float
    build_ms: float  # per-block data built on the render thread (geometry-splitting's trees)
    build_cpu_ms: float  # the render thread's CPU in that (build_ms is wall time)
    gpu_ms: float
    loaded_mb: float
    resident_mb: float
    strategy_gpu_mb: float  # the strategy's own GPU buffers (meshes, quadtree textures)
    stalled: bool
    clamped: int
    visible_blocks: int  # blocks in the view (0: the camera sees none of the DEM)
    drawn_px: int  # terrain pixels drawn (0 with triangles: all below a pixel, or masked)


def write_rows(out: Path, rows: list[FlyRow]) -> None:
    """``frames.csv``: one line per frame flown."""
    with open(out / "frames.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        for row in rows:
            w.writerow(asdict(row))


def warn_frames_below_ground(store: TerrainStore, cameras: Sequence[Camera]) -> np.ndarray:
    """Log a warning when cameras of the path are below the terrain under them (those frames
    show it from below); each camera's depth below the ground (0: not below)."""
    return warn_path_below_ground(store, cameras, "they show the terrain from below", log)


def save_frame(image: np.ndarray, path: Path) -> None:
    """Write the RGB ``image`` as the PNG ``path`` whole or not at all (encoded in memory,
    then ``tiler.atomic.write_atomic``): a flight stopped while a frame is written (Ctrl-C, a
    full disk) leaves no cut-short PNG that looks like a frame."""
    write_atomic(os.path.abspath(path), encode_image(image, Path(path).with_suffix(".png")))


class ImageFormatError(RenderError, ValueError):
    """An image file's extension names a format that cannot hold the picture as it is
    (``resized``: the size the file would have held instead, when that is why)."""

    def __init__(self, message: str, resized: tuple[int, int] | None = None) -> None:
        super().__init__(message)
        self.resized = resized


#: Netpbm extensions and the magic numbers of the kind of file each names (Pillow writes an
#: RGB picture as a P6 pixmap whatever the extension: a ``.pbm`` bitmap or ``.pfm`` float map
#: reader then finds something else)
NETPBM_MAGIC = {".pbm": (b"P1", b"P4"), ".pgm": (b"P2", b"P5"), ".pfm": (b"Pf", b"PF")}


def encode_image(image: np.ndarray, path: str | Path) -> bytes:
    """The RGB ``image`` (rows x columns x 3, uint8) encoded in the format of ``path``'s
    extension; :class:`ImageFormatError` when that format cannot hold it as it is: no encoder
    for an RGB picture (``.xbm``, ``.palm``, ``.h5`` ...), a Netpbm extension naming another
    kind of file (:data:`NETPBM_MAGIC`), or a file whose picture is not ``image``'s size (an
    ``.ico`` holds at most 256 x 256, an ``.icns`` is square)."""
    from PIL import Image

    Image.init()
    suffix = Path(path).suffix.lower()
    fmt = Image.registered_extensions().get(suffix)
    use = "; use .png (lossless), .jpg or .tif"
    if fmt is None:
        raise ImageFormatError(
            f"cannot tell the image format of {str(path)!r} from its extension "
            f"{suffix or '(none)'!r}{use}"
        )
    buf = io.BytesIO()
    try:
        Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)).save(buf, format=fmt)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, OSError) and exc.errno is not None:  # an I/O error, not the format
            raise
        raise ImageFormatError(
            f"cannot write the picture as {fmt} ({suffix}): {exc}{use}"
        ) from None
    data = buf.getvalue()
    if suffix in NETPBM_MAGIC and data[:2] not in NETPBM_MAGIC[suffix]:
        kind = {".pbm": "bitmap", ".pgm": "greymap", ".pfm": "float map"}[suffix]
        raise ImageFormatError(
            f"a {suffix} file is a Netpbm {kind}, not a colour picture (it would be a "
            f"{data[:2].decode(errors='replace')} pixmap under that name); use .ppm, or .png "
            "(lossless), .jpg or .tif"
        )
    try:  # the header only: the size the file's reader will see
        with Image.open(io.BytesIO(data)) as im:
            got = im.size
    except Exception:  # noqa: BLE001 - no reader here (EPS needs Ghostscript, PDF has none)
        got = None
    want = (int(image.shape[1]), int(image.shape[0]))
    if got is not None and got != want:
        raise ImageFormatError(
            f"{fmt} files ({suffix}) cannot hold a {want[0]}x{want[1]} picture: it would be "
            f"{got[0]}x{got[1]}{use}",
            resized=got,
        )
    return data


def _remove_if_empty(out: Path, created: bool) -> None:
    """Remove ``out`` when this run created it and an error left nothing in it."""
    if created and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def flythrough(
    store: TerrainStore,
    cameras: Sequence[Camera],
    out_dir: str | Path,
    *,
    tau: float = 1.0,
    metric: str = "qiu",
    patch_log2: int = 4,
    workers: int = 2,
    budget_mb: float = 256.0,
    fps: float = 30.0,
    save_every: int = 1,
    on_frame: Callable[[FlyRow], None] | None = None,
    lod: str = DEFAULT,
    options: ViewOptions | None = None,
    background_builds: bool = True,
) -> tuple[list[FlyRow], dict[str, Any]]:
    """Stream and render each camera with strategy ``lod``; write PNG frames and
    ``frames.csv`` into ``out_dir`` (``options``, when given, supplies ``lod``, ``tau``,
    ``metric`` and ``patch_log2``, and how frames are drawn). A path none of whose frames
    draws terrain raises :class:`streamer.errors.PathOutOfViewError` (its PNGs removed); an
    error that stops the flight is raised after ``frames.csv`` of the frames flown is written
    (their count: ``exc.frames_flown``). ``background_builds``: per-block data a level change
    needs is built on a worker thread, the frames meanwhile drawing with what it replaces
    (:meth:`render.strategies.base.Strategy.build_in_background`; False: every frame builds
    what it draws first, as a one-shot render)."""
    o = options or ViewOptions(lod=lod, tau=tau, metric=metric, patch_log2=patch_log2)
    lod, tau, metric = o.lod, o.tau, o.metric
    if not cameras:
        raise RenderError("the camera path has no frames")
    warn_frames_below_ground(store, cameras)
    out = Path(out_dir)
    created = not out.exists()  # a folder made here and left empty by an error is removed
    out.mkdir(parents=True, exist_ok=True)
    r = TerrainRenderer(store, RenderConfig(size=cameras[0].viewport, patch_log2=o.patch_log2))
    strat = get_strategy(lod, r, **o.strategy_options())
    if background_builds:
        strat.build_in_background()
    draw = o.draw_options()
    rows: list[FlyRow] = []
    flown: list[dict[str, Any]] = []  # the frames' FrameStats, for streamer.run.frames_summary
    pending: Path | None = None  # a frame's PNG written, its row not yet in rows
    try:
        with open_session(
            store,
            budget_mb=budget_mb,
            workers=workers,
            tau=tau,
            metric=stream_metric(lod, metric),
            patch_log2=session_patch_log2(strat, r),  # (chunk-tessellation: its chunks)
            culling="hull",
            fps=fps,
            nodata=o.nodata,
            raise_on_failure=False,  # fly on, as `stream`: failures are in the summary's verdict
        ) as session:
            seen = False  # frames wait for their data until the first one that sees the DEM
            for i, cam in enumerate(cameras):
                step = frame_step(
                    session, strat, cam, tau, metric, dt=1.0 / fps, wait=not seen, options=draw
                )
                frame, st, ms = step.frame, step.stats, step.selection_ms
                seen = seen or frame.stats.visible_blocks > 0
                if save_every and i % save_every == 0:
                    pending = out / f"frame_{i:05d}.png"
                    save_frame(r.image(), pending)
                fs = frame.stats
                row = FlyRow(
                    frame=i,
                    triangles=st.triangles,
                    patches=st.patches,
                    selection_ms=ms,
                    build_ms=strat.build_ms,
                    build_cpu_ms=strat.build_cpu_ms,
                    gpu_ms=st.frame_ms,
                    loaded_mb=(fs.realtime_bytes + fs.prefetched_bytes) / 2**20,
                    resident_mb=fs.resident_bytes / 2**20,
                    strategy_gpu_mb=strat.own_gpu_bytes() / 2**20,
                    stalled=fs.stalled,
                    clamped=st.clamped,
                    visible_blocks=fs.visible_blocks,
                    drawn_px=r.drawn_pixels() if st.triangles else 0,
                )
                rows.append(row)
                flown.append(asdict(fs))
                pending = None
                if on_frame:
                    on_frame(row)
            # reads still in flight may finish, fail or never answer: say which (as `stream`)
            unfinished, summary = close_for_verdict(session)
    except BaseException as exc:  # a flight stopped midway (Ctrl-C too) keeps its frames' figures
        if pending is not None:  # the frame it stopped at is not in frames.csv: nor its PNG
            pending.unlink(missing_ok=True)
        if rows:
            write_rows(out, rows)
            exc.frames_flown = len(rows)  # type: ignore[attr-defined]
        else:
            _remove_if_empty(out, created)
        raise
    finally:
        try:
            strat.close()  # (its worker stopped: bounded, an error if a build hangs)
        finally:
            r.close()
    problem = flight_problem(summary, unfinished, str(getattr(store, "url", store)))
    empty = [x.frame for x in rows if x.drawn_px == 0]
    if len(empty) == len(rows):  # blank frames are not a fly-through: none is left behind
        for i in range(0, len(rows), save_every) if save_every else ():  # only this run's
            (out / f"frame_{i:05d}.png").unlink(missing_ok=True)
        _remove_if_empty(out, created)
        if not seen:
            raise out_of_view(store, len(rows))
        if any(x.triangles for x in rows):
            raise EmptyViewError(
                f"none of the {len(rows)} frame(s) drew a terrain pixel, though "
                f"{sum(x.triangles > 0 for x in rows)} drew triangles: they were all smaller "
                "than a pixel or outside the view, or the terrain is too sparse to draw (a "
                "triangle with a nodata corner is not drawn); fly closer to the DEM"
            )
        raise RenderError(
            f"none of the {len(rows)} frame(s) drew terrain, though "
            f"{sum(x.visible_blocks > 0 for x in rows)} saw the DEM: none of its levels was "
            "resident when they were drawn; " + (problem or "run `terrastream verify` on the store")
        )
    write_rows(out, rows)
    tri = np.array([x.triangles for x in rows])
    in_frames = sum(int(f["realtime_bytes"]) + int(f["prefetched_bytes"]) for f in flown)
    thrown = sum(int(f["discarded_bytes"]) for f in flown)
    cut = frames_summary(summary, flown)  # the session's loads and discards cut to the frames
    summary = {
        "frames": len(rows),
        "mean_triangles": float(tri.mean()),
        "max_triangles": int(tri.max()),
        "mean_selection_ms": float(np.mean([x.selection_ms for x in rows])),
        "max_selection_ms": float(np.max([x.selection_ms for x in rows])),
        "mean_build_ms": float(np.mean([x.build_ms for x in rows])),
        "max_build_ms": float(np.max([x.build_ms for x in rows])),
        "max_build_cpu_ms": float(np.max([x.build_cpu_ms for x in rows])),
        "mean_gpu_ms": float(np.mean([x.gpu_ms for x in rows])),
        "max_strategy_gpu_mb": float(np.max([x.strategy_gpu_mb for x in rows])),
        "stall_frames": int(sum(x.stalled for x in rows)),
        "clamped_frames": int(sum(x.clamped > 0 for x in rows)),
        "empty_frames": len(empty),
        "first_empty_frame": empty[0] if empty else None,
        # of the empty frames (no terrain pixel), those that saw none of the DEM, and those
        # whose triangles covered no pixel (the others were stalled: nothing resident)
        "unseen_frames": int(sum(x.visible_blocks == 0 for x in rows if x.triangles == 0)),
        "pixelless_frames": int(sum(x.triangles > 0 and x.drawn_px == 0 for x in rows)),
        # the frames' loads, as frames.csv sums them; a warm-up's (none here) and reads ahead
        # that finished while the session closed, after the last frame, apart: the three
        # add up to the session's loads (streamer.run.frames_summary)
        "loaded_mb": float(in_frames / 2**20),
        "warmup_mb": float(cut["warmup_bytes"] / 2**20),
        "loaded_after_frames_mb": float(cut["loaded_after_frames_bytes"] / 2**20),
        # levels read but thrown away on arrival, never cached, split the same way
        "discarded_mb": float(thrown / 2**20),
        "warmup_discarded_mb": float(cut["warmup_discarded_bytes"] / 2**20),
        "discarded_after_frames_mb": float(cut["discarded_after_frames_bytes"] / 2**20),
        "io_errors": int(summary["io_errors"]),
        "failing_blocks": int(summary["failing_blocks"]),
        # why the fly-through is incomplete (streamer.run.flight_problem), or None
        "problem": problem,
        # the frames' peak, as frames.csv's resident_mb shows it (reads that arrived while
        # the session closed, after the last frame, are not the flight's)
        "peak_resident_mb": float(summary["peak_resident_bytes_frames"] / 2**20),
    }
    return rows, summary
