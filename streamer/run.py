"""Fly a camera path through a session in real time and collect per-frame statistics.

Used by ``terrastream stream`` and ``bench/prefetch.py``. Frames are paced at ``fps`` on the
wall clock (so store latency is real): frame ``i`` is due at ``t0 + i / fps``; the loop sleeps
until then, calls :meth:`Session.update` (non-blocking, except the first frame, which waits
so the fly-through starts with its data), and records the frame's stats.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from streamer import paths
from streamer.camera import Camera
from streamer.clip import fit_clip
from streamer.errors import PathError, PathOutOfViewError
from streamer.loader import THREAD_PREFIX
from streamer.session import FrameStats, Session
from tiler.errors import StoreChangedError
from tiler.store import TerrainStore

log = logging.getLogger(__name__)

PATH_KINDS = ("default", "line", "circle", "canyon", "teleports")
#: what a flight streams and counts stalls over: Qiu's triangle, or the frustum hull drawn
CULLINGS = ("qiu", "hull")
T = TypeVar("T")


@dataclass(frozen=True)
class RunResult:
    """Per-frame statistics and the session summary of one fly-through."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]

    def to_json(self, path: str | Path) -> None:
        """Write ``{"frames": rows, "summary": summary}``."""
        Path(path).write_text(json.dumps({"frames": self.rows, "summary": self.summary}, indent=1))


def store_height_fn(store: TerrainStore, level: int | None = None) -> Callable:
    """``height(x, y)`` by bilinear interpolation of one level of the store (blocks cached)."""
    lv = max(0, store.k - 4) if level is None else level
    step = 1 << (store.k - lv)
    grid = store.grid
    cache: dict[tuple[int, int], np.ndarray] = {}
    zmid = float(np.nanmean(store.index.zmax))

    def height(x: float, y: float) -> float:
        r, c = grid.world_to_sample(x, y)
        r = min(max(float(r), 0.0), grid.height - 1.0)
        c = min(max(float(c), 0.0), grid.width - 1.0)
        br, bc = (int(v) for v in grid.block_of_sample(int(r), int(c)))
        if not store.index.exists[br, bc]:
            return zmid
        if (br, bc) not in cache:
            cache[(br, bc)] = store.read_block((br, bc), lv).astype(np.float64)
        g = cache[(br, bc)]
        lr, lc = (r - br * grid.step) / step, (c - bc * grid.step) / step
        r0, c0 = min(int(lr), g.shape[0] - 2), min(int(lc), g.shape[1] - 2)
        fr, fc = lr - r0, lc - c0
        top = g[r0, c0] * (1 - fc) + g[r0, c0 + 1] * fc
        bot = g[r0 + 1, c0] * (1 - fc) + g[r0 + 1, c0 + 1] * fc
        return float(top * (1 - fr) + bot * fr)

    return height


def make_path(
    store: TerrainStore,
    kind: str = "default",
    *,
    frames: int = 600,
    fps: float = 60.0,
    speed: float | None = None,
    path_file: str | Path | None = None,
    seed: int = 0,
    **camera_kw: Any,
) -> list[Camera]:
    """A fly-through over the store: a keyframe file, or one of :data:`PATH_KINDS`.

    Speeds are world units per second (default: one block edge per second). A keyframe file's
    cameras see the whole DEM: their clipping planes are :func:`streamer.clip.fit_clip`'s
    unless ``near`` or ``far`` is given.
    """
    grid = store.grid
    zmin, zmax = store.meta.extra.get("value_range", (0.0, 0.0))
    edge = grid.step * grid.dx
    v = edge if speed is None else float(speed)
    if path_file is not None:
        if kind != "default" or speed is not None:  # (the file's keyframes set both)
            log.warning(
                "the keyframe file %s sets the path and its speed: the path kind %r and "
                "speed %s are not used",
                path_file,
                kind,
                "(default)" if speed is None else f"{speed:g}",
            )
        cams = paths.keyframes(path_file, frames, **camera_kw)
        if "near" in camera_kw or "far" in camera_kw:
            return cams
        # clipping planes as `render --camera` chooses them: a far plane beyond the whole DEM
        # (a fixed one left a camera 150 km up seeing nothing), a near one from the clearance
        return [fit_clip(store, c) for c in cams]
    x0, y0, x1, y1 = grid.extent
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    height = zmax + max(0.1 * (zmax - zmin), 0.02 * edge)
    dist = v * frames / fps
    camera_kw.setdefault("far", max(8 * edge, 4 * (height - zmin) + dist / 4))
    camera_kw.setdefault("near", max(0.5, 0.002 * (height - zmin)))
    if kind == "default":
        kw = {k: camera_kw[k] for k in ("viewport", "fov_y") if k in camera_kw}
        return paths.default_flythrough(grid, zmin, zmax, frames, fps, speed=v, **kw)
    if kind == "line":
        # (frames - 1 steps between its first and last frame: at v each)
        half = min(v * max(frames - 1, 1) / fps, math.hypot(x1 - x0, y1 - y0)) / 2
        a = np.array([cx, cy]) - half * np.array([1.0, 1.0]) / math.sqrt(2)
        b = np.array([cx, cy]) + half * np.array([1.0, 1.0]) / math.sqrt(2)
        why = "it is capped at the DEM's diagonal"
        _say_speed(kind, 2 * half / max(frames - 1, 1) * fps, v, speed, why)
        return paths.line((*a, height), (*b, height), frames, **camera_kw)
    if kind == "circle":
        radius = min(0.35 * min(x1 - x0, y1 - y0), v * frames / fps / (2 * math.pi))
        radius = max(radius, edge / 4)
        why = "one loop of a radius between a quarter block edge and 0.35 of the DEM's side"
        _say_speed(kind, 2 * math.pi * radius / frames * fps, v, speed, why)  # (frames steps)
        return paths.circle((cx, cy), radius, height, frames, look="tangent", **camera_kw)
    if kind == "canyon":
        fn = store_height_fn(store)
        half = min(dist, 0.8 * math.hypot(x1 - x0, y1 - y0)) / 2
        a = (cx - half / math.sqrt(2), cy - half / math.sqrt(2))
        b = (cx + half / math.sqrt(2), cy + half / math.sqrt(2))
        clearance = max(0.01 * edge, 0.05 * (zmax - zmin))
        return paths.canyon(fn, a, b, frames, clearance, **camera_kw)
    if kind == "teleports":
        bounds = (x0, y0, zmax, x1, y1, height + 0.2 * (zmax - zmin))
        return paths.teleports(bounds, frames, seed, max(1, int(fps)), **camera_kw)
    raise PathError(f"unknown path kind {kind!r}; choose one of {', '.join(PATH_KINDS)}")


def _say_speed(kind: str, flown: float, v: float, asked: float | None, why: str) -> None:
    """Warn when a path fitted to the DEM flies at ``flown`` units/s, more than 5 % off the
    speed ``v`` asked (``asked``: the option's value, None when not given), and why."""
    if asked is None:
        return
    if abs(flown - v) > 0.05 * v:
        log.warning(
            "the %s path flies at %.4g units/s, not the --speed %.4g asked: %s (--frames and "
            "--fps set how long it is flown)",
            kind,
            flown,
            v,
            why,
        )


def paced(items: Iterable[T], fps: float) -> Iterator[T]:
    """Yield ``items`` at ``fps`` on the wall clock, as a viewer shows frames.

    Item 0 comes at once; the clock starts when the caller asks for item 1 (frame 0 shown,
    after any wait), and item ``i`` is due ``i / fps`` after that: the generator sleeps until
    then (a late caller gets the next item at once). Example::

        for cam in paced(cameras, fps=60):
            frame = session.update(cam, 1 / 60)
    """
    rate = float(fps)
    if not (rate > 0 and math.isfinite(rate)):
        raise PathError(f"fps must be a positive number, got {fps!r}")
    t0 = 0.0
    for i, item in enumerate(items):
        if i == 1:
            t0 = time.perf_counter()  # frame 0 has been shown
        if i >= 1:
            delay = t0 + i / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        yield item


def run_flythrough(
    session: Session,
    cameras: list[Camera],
    *,
    realtime: bool = True,
    first_wait: bool = True,
    on_frame: Callable[[int, FrameStats], None] | None = None,
) -> RunResult:
    """Update the session once per camera, paced at the session's fps; collect every frame.

    With ``first_wait`` the session is warmed up for the first camera (see
    :meth:`Session.warm_up`; reported as ``warmup_ms``/``warmup_bytes``, and
    ``warmup_discarded_bytes``) and frame 0 waits.
    An exception that stops the flight carries the frames flown so far as ``exc.partial``
    (a :class:`RunResult`). Either summary's figures are the rows' (:func:`frames_summary`).
    """
    fps = session.config.fps
    rows: list[dict[str, Any]] = []
    try:
        if first_wait and cameras:
            session.warm_up(cameras[0])
        for i, cam in enumerate(paced(cameras, fps) if realtime else cameras):
            frame = session.update(cam, 1.0 / fps, wait=first_wait and i == 0)
            row = asdict(frame.stats)
            rows.append(row)
            if on_frame is not None:
                on_frame(i, frame.stats)
    except Exception as exc:
        # the frames flown so far, for the caller's report (stream --json/--plot); a frame
        # the session counted before raising (LoadError carries it) is one of them
        ended = getattr(exc, "frame", None)
        stats = getattr(ended, "stats", None)
        if stats is not None and (not rows or rows[-1]["frame"] != stats.frame):
            rows.append(asdict(stats))
        partial = RunResult(rows=rows, summary=frames_summary(session.summary(), rows))
        exc.partial = partial  # type: ignore[attr-defined]
        raise
    return RunResult(rows=rows, summary=frames_summary(session.summary(), rows))


def frames_summary(summary: dict[str, Any], rows: list[dict[str, Any]]) -> dict[str, Any]:
    """``summary`` (a live session's) with its loaded and discarded bytes those of the
    warm-ups and the frames ``rows``.

    Loaders keep reading after the last frame (until the session closes, or while an error
    stops the flight), so a session's ``loaded_bytes`` may exceed the warm-ups' (``warmup_bytes``,
    every warm-up's, before or between the frames) plus the frames' real-time and prefetched
    bytes: ``loaded_bytes`` becomes that sum (``wasted_bytes``
    follows) and ``loaded_after_frames_bytes`` says what arrived after the last frame. Likewise
    ``discarded_bytes`` (read but thrown away on arrival) becomes ``warmup_discarded_bytes``
    plus the rows' ``discarded_bytes``, and ``discarded_after_frames_bytes`` the rest
    (``discarded_levels`` stays the session's count).
    """
    out = dict(summary)
    in_frames = int(out.get("warmup_bytes", 0)) + sum(
        int(r["realtime_bytes"]) + int(r["prefetched_bytes"]) for r in rows
    )
    total = int(out.get("loaded_bytes", in_frames))
    out["loaded_bytes"] = in_frames
    out["loaded_after_frames_bytes"] = max(0, total - in_frames)
    out["wasted_bytes"] = max(0, in_frames - int(out.get("used_bytes", 0)))
    thrown = int(out.get("warmup_discarded_bytes", 0)) + sum(
        int(r.get("discarded_bytes", 0)) for r in rows
    )
    total = int(out.get("discarded_bytes", thrown))
    out["discarded_bytes"] = thrown
    out["discarded_after_frames_bytes"] = max(0, total - thrown)
    return out


def out_of_view(store: TerrainStore, frames: int) -> PathOutOfViewError:
    """The error for a camera path of ``frames`` frames none of which sees the DEM."""
    x0, y0, x1, y1 = store.grid.extent
    return PathOutOfViewError(
        f"none of the {frames} frame(s) of the camera path sees the DEM (x {x0:.0f} .. "
        f"{x1:.0f}, y {y0:.0f} .. {y1:.0f}): there is nothing to stream or draw; point the "
        "path at the terrain"
    )


def require_view(result: RunResult, store: TerrainStore) -> None:
    """Raise :class:`PathOutOfViewError` when no frame of ``result`` had a block in view."""
    if result.rows and not any(r["visible_blocks"] for r in result.rows):
        raise out_of_view(store, len(result.rows))


#: seconds ``stream`` waits after the flight for reads still in flight (``Session.close``)
CLOSE_WAIT_S = 10.0
#: summary keys ``stream --json`` repeats as they stood after that wait (``at_close``)
AT_CLOSE = (
    "io_errors",
    "failed_blocks",
    "failing_blocks",
    "failing_blocks_needed",
    "failing_blocks_unreachable",
    "last_read_error",
    "store_changed",
)


def close_for_verdict(session: Session) -> tuple[list[str], dict[str, Any]]:
    """Close a flown session (waiting :data:`CLOSE_WAIT_S` for reads in flight) and return the
    threads left running and the summary then, for :func:`flight_problem`. A store change
    seen by a read during that wait is not raised: the summary's ``store_changed`` says it."""
    try:
        unfinished = session.close(CLOSE_WAIT_S)
    except StoreChangedError:
        unfinished = session.unfinished
    return unfinished, session.summary()


def flight_problem(summary: dict[str, Any], unfinished: list[str], url: str) -> str | None:
    """Why a finished flight must not exit 0 (None: it may).

    ``summary`` is the session's summary taken after :meth:`Session.close` (which waited
    :data:`CLOSE_WAIT_S` for reads in flight) and ``unfinished`` the threads close left
    running: a read never answered; blocks a frame needed whose latest read failed, or blocks
    that failed every retry (worded by cause, the server's or the store's, and by whether a
    frame needed them or they were only read ahead); or nothing loaded at all. A read ahead
    that failed once and may still work is not a failure; a store replaced or rewritten while
    it was streamed (``store_changed``) comes first."""
    if summary.get("store_changed"):
        return (
            "the store was replaced or rewritten while it was streamed: stream it again "
            f"({summary['store_changed']})"
        )
    reads = [n for n in unfinished if n.startswith(THREAD_PREFIX)]
    if reads:
        return (
            f"{len(reads)} read(s) of {url!r} were still unanswered {CLOSE_WAIT_S:.0f} s after "
            "the flight ended: the server stopped answering; check it (an http(s) store's "
            "reads give up after the storage option 'timeout', default 30 s)"
        )
    failed = len(summary.get("failed_blocks") or [])
    needed = int(summary.get("failing_blocks_needed", 0))
    if not failed and not needed:  # a read ahead that failed and may yet work is no failure
        if summary.get("loaded_bytes"):
            return None
        return "no level could be loaded; run `terrastream verify` on the store or check its server"
    if needed:
        what = f"{needed} block(s) a frame needed could not be read by the end"
        what += f" ({failed} failed every retry)" if failed else ""
    else:
        what = (
            f"{failed} block(s) read ahead of the camera failed every retry (no frame needed them)"
        )
    last = summary.get("last_read_error") or "unknown"
    if summary.get("failing_blocks_unreachable", 0) == summary.get("failing_blocks", 0):
        cause = "the server or the network failed, not the store: check them and stream again"
    else:
        cause = f"run `terrastream verify {url}` (the store may be damaged)"
    return f"{what}; {cause} (latest error: {last})"


def plot_run(result: RunResult, out: str | Path, title: str = "") -> None:
    """Plot needed / real-time / prefetched MiB and I/O ms per frame (Qiu's Table 3) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.rows
    f = np.arange(len(rows))
    mb = 1 / 2**20
    fig, ax = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    ax[0].plot(f, [r["needed_bytes"] * mb for r in rows], label="needed MiB (visible levels)")
    ax[0].plot(f, [r["resident_bytes"] * mb for r in rows], label="resident MiB")
    ax[0].legend(loc="upper right")
    ax[1].plot(
        f, [r["realtime_bytes"] * mb for r in rows], label="real-time loaded MiB", color="C3"
    )
    ax[1].plot(f, [r["prefetched_bytes"] * mb for r in rows], label="prefetched MiB", color="C2")
    stalls = [i for i, r in enumerate(rows) if r["stalled"]]
    if stalls:
        ax[1].scatter(stalls, [0] * len(stalls), marker="|", color="k", label="stall")
    ax[1].legend(loc="upper right")
    ax[2].plot(f, [r["io_ms"] for r in rows], label="I/O ms (workers)")
    ax[2].plot(f, [r["update_ms"] for r in rows], label="update ms (caller)")
    ax[2].set_xlabel("frame")
    ax[2].legend(loc="upper right")
    s = result.summary
    fig.suptitle(
        title
        or f"{s['frames']} frames, {s['stall_frames']} stalls, "
        f"peak resident {s['peak_resident_bytes'] * mb:.1f} MiB"
    )
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
