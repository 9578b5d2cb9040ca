"""Streaming sessions: frustum-extension prefetching into a byte-budgeted cache (Qiu et al. 4).

A session is three parts: a pure :class:`~streamer.planner.Planner` (which blocks, at which
levels, for which pose), a :class:`~streamer.loadqueue.LoadQueue` (keys, priorities,
cancellation, backoff) and a :class:`~streamer.loader.Loader` that drains it on a named thread
pool (``terrastream-load_N``) with completion callbacks.

Each :meth:`Session.update` (the caller's thread) only plans: it finds the visible set ``M``
and the level each block needs (lock-free reads of the error table), pins those levels in the
cache and queues what is missing; the prefetch plan for the extension ``N`` runs on a
one-thread planning pool (``terrastream-plan_0``). Loads bring blocks up one level at a time,
coarsest first across blocks: visible blocks first, then prefetch blocks by screen error.
Queued work for blocks that left ``N`` is dropped (cancelled).

Sessions heal: a failed read is retried with exponential backoff (capped at
``max_backoff_s``) for as long as the block is wanted. After ``retries`` failures in a row the
block is *failed*: named in :attr:`Frame.failed`, counted in ``FrameStats.failed_blocks`` and
``summary()["failed_blocks"]``, and (with ``raise_on_failure``) the next ``update`` raises
:class:`LoadError` once, carrying the frame; the session stays usable. A visible block with no
resident level is a hole, counted in ``FrameStats.holes``: never silent.

Threads: ``close()`` joins the session's own threads (bounded). zarr runs its I/O on a shared
asyncio event-loop thread of its own (``zarr_io``-style names), created once per process and
reused by every store; those are zarr's, not the session's, and their number does not grow
with the number of sessions (tested).

Bytes are decoded level bytes (the source dtype), the quantity held in memory and budgeted.
Parts kept apart: pinning a frame's levels and the budget error (:mod:`streamer.pins`),
closing the threads (:mod:`streamer.sessionthreads`), the arguments' checks
(:mod:`streamer.sessionargs`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace
from itertools import repeat
from typing import Any

import numpy as np

from streamer import levels as levels_kernels
from streamer.blockside import Side
from streamer.cache import Block, PinChanges
from streamer.camera import Camera
from streamer.errors import (
    BudgetError,
    LoadError,
    LodError,
    SessionClosedError,
    SessionThreadError,
    StreamerError,
)
from streamer.frames import Frame, FrameStats, SessionConfig
from streamer.gcfreeze import freeze_heap
from streamer.loader import READ_ERRORS, Loader
from streamer.loadreport import failing as loader_failing
from streamer.lod import FIELD_FOR_METRIC
from streamer.pins import UNBOUNDED_TAU, levels_of, pin_and_queue, read_error_tables, to_queue
from streamer.planner import Planner
from streamer.planthread import PlanThread
from streamer.sessionargs import check_camera, check_dt, check_timeout
from streamer.sessionthreads import SessionThreads
from streamer.waits import wait_for, wait_idle, waiting
from tiler.crs import require_projected
from tiler.errors import StoreIncompleteError
from tiler.layout import level_size
from tiler.store import TerrainStore, open_store
from tiler.vertical import height_dtype


class Session:
    """A streaming session over one store. Use as a context manager; not for sharing between
    callers (one thread calls :meth:`update`)."""

    def __init__(
        self,
        store: TerrainStore | str,
        config: SessionConfig | None = None,
        *,
        read_hook: Callable[[Block, int], None] | None = None,
    ) -> None:
        self.store = store if isinstance(store, TerrainStore) else open_store(store)
        if not self.store.meta.complete:  # (opened with allow_incomplete: its index is empty
            # until the tiling finishes, so every frame would see nothing and report no hole)
            raise StoreIncompleteError(
                f"store {self.store.url!r} is not finished: a session streams finished stores "
                "only; run the 'terrastream tile' command that writes it to completion"
            )
        require_projected(self.store)  # degrees beside metres cannot be streamed
        self._config = config or SessionConfig()
        self.grid = self.store.grid
        # decoded bytes: heights of a scaled store (band scale/offset, feet) decode to float64
        itemsize = np.dtype(height_dtype(self.store.meta)).itemsize
        self.level_bytes = [level_size(i) * itemsize for i in range(self.store.k + 1)]
        self._cum_bytes = [sum(self.level_bytes[: i + 1]) for i in range(self.store.k + 1)]
        self._cum_array = np.array(self._cum_bytes, dtype=np.int64)  # (indexed by level arrays)
        field_name = FIELD_FOR_METRIC.get(self.config.metric, "qiu")
        self.loader = Loader(self.store, self.config, self.level_bytes, field_name, read_hook)
        self.cache = self.loader.cache
        self.totals = self.loader.totals
        idx = self.store.index
        self.planner = Planner(
            self.grid, self.store.k, idx.exists, idx.zmin, idx.zmax, self.loader.errors, self.config
        )
        self._cv = self.loader.cv
        self._prev: Camera | None = None
        self._clock0: float | None = None  # when frame 0 was shown (its update returned)
        self._due = 0.0  # due time of the frame being made
        self._shown: dict[Block, tuple[int, int]] = {}  # the last frame's blocks
        # the cache's finest resident levels as of the latest frame (blocks holding any),
        # kept from LevelCache.take_level_changes: the caller's copy, read without the lock
        self._resident: dict[Block, int] = {}
        self._resident_version = 0  # +1 whenever that copy changes
        self._updating = threading.Lock()  # held by the thread inside update() (one at a time)
        self._peak_frames = 0  # the largest FrameStats.resident_bytes of the frames so far
        # account_hull: frames with a block of the hull holding no level (None: not accounted)
        self._hull_hole_frames: int | None = None
        self._plans = PlanThread(self.planner, self.loader, self.config.workers)
        self._threads = SessionThreads(self.loader, self._plans)

    @property
    def config(self) -> SessionConfig:
        """The session's settings (assigning a new one reaches the planner and the loader)."""
        return self._config

    @config.setter
    def config(self, cfg: SessionConfig) -> None:
        self._check_open("its settings cannot change")
        if cfg.workers != self._config.workers or cfg.budget_mb != self._config.budget_mb:
            raise StreamerError("workers and budget_mb cannot change during a session")
        if cfg.nodata != self._config.nodata:  # the error table was filled under the old rule
            raise StreamerError("the nodata rule cannot change during a session")
        self._config = self.planner.config = self.loader.config = cfg

    @property
    def stall_set(self) -> str:
        """The set stalls and holes are counted over: "triangle" (culling="qiu") or "hull"."""
        return "triangle" if self._config.culling == "qiu" else "hull"

    @property
    def _read_hook(self) -> Callable[[Block, int], None] | None:
        return self.loader.read_hook

    @_read_hook.setter
    def _read_hook(self, hook: Callable[[Block, int], None] | None) -> None:
        self.loader.read_hook = hook

    # -- context management ---------------------------------------------------------------

    def __enter__(self) -> Session:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if self._threads.closed:  # closed in the block: no second wait for reads that hang
            return
        self._threads.close(10.0, raise_bug=exc_type is None)  # never mask the exception

    def close(self, timeout_s: float = 10.0) -> list[str]:
        """Stop the loader and planning threads, waiting at most ``timeout_s`` for reads in
        flight; the names of threads still running then (a read the server never answers).
        An exception a loader or planning thread raised that no :meth:`update` re-raised yet
        is raised here, once the threads are stopped. Closing again waits (as long) for the
        threads still running and names those still running then.

        A closed session plans and loads nothing more: :meth:`update`, :meth:`warm_up`,
        :meth:`set_tau` and assigning :attr:`config` raise :class:`SessionClosedError`. What it
        held stays readable, for the report and the last frame's drawing: :meth:`summary`,
        :meth:`levels`, :meth:`block_side`, :meth:`resident_levels` (see :attr:`closed`)."""
        return self._threads.close(timeout_s, raise_bug=True)

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called (its threads may still be finishing: see
        :attr:`unfinished`): a reader of :meth:`levels` that must not take a closed
        session's data (it holds no newer level) checks it first."""
        return self._threads.closed

    @property
    def unfinished(self) -> list[str]:
        """The session's threads still running when the latest :meth:`close` returned."""
        return self._threads.unfinished

    def set_tau(self, tau: float) -> None:
        """Change the screen-space error threshold for what is drawn *and* what is streamed."""
        self._check_open(f"set_tau({tau!r}) cannot change its threshold")
        if isinstance(tau, bool) or not isinstance(tau, int | float | np.integer | np.floating):
            raise LodError(f"tau must be a number of pixels > 0, got {tau!r}")
        self.config = replace(self.config, tau=float(tau))  # validated by SessionConfig

    # -- planning -------------------------------------------------------------------------

    def _check_open(self, what: str) -> None:
        """:class:`SessionClosedError` saying ``what`` cannot be done, once closed."""
        if self._threads.closed:
            raise SessionClosedError(
                f"this session is closed (close() was called): {what}; open a new session "
                "to stream again"
            )

    def _pin_and_queue(
        self,
        needed: dict[Block, int],
        todo: list[Block] | None = None,
        need: int | None = None,
        changes: PinChanges | None = None,
        *,
        camera: Camera,
    ) -> int:
        return pin_and_queue(
            self.loader, self.planner, needed, self._cum_bytes, todo, need, changes, camera=camera
        )

    def _read_error_tables(self, blocks: list[Block]) -> int:
        """:func:`streamer.pins.read_error_tables` of this session's loader."""
        return read_error_tables(self.loader, blocks)

    def _raise_background_error(self, *, fatal: bool = True) -> None:
        self._threads.raise_error(fatal=fatal)

    # -- the frame ------------------------------------------------------------------------

    def warm_up(self, camera: Camera, timeout_s: float | None = None) -> dict[str, float]:
        """Before a flight: load everything the plan for ``camera`` wants — the visible levels
        and the prefetch around them — and return ``{"ms", "bytes"}`` spent, and
        ``"discarded_bytes"``: those read meanwhile but thrown away on arrival (in no frame's
        ``FrameStats.discarded_bytes``; ``summary()["warmup_discarded_bytes"]``).

        Each warm-up adds to the session's warm-up figures (``summary()["warmups"]``,
        ``"warmup_ms"``, ``"warmup_bytes"``, ``"warmup_discarded_bytes"``: all warm-ups'). A
        warm-up after frames keeps what the loaders counted since the previous frame before it
        began for the next frame (its real-time, prefetched, late and discarded bytes, its
        I/O time); what arrives during it is the warm-up's alone.

        Without it the first second of a flight stalls while the prefetch ring fills; Qiu et
        al. likewise count the first frame's load apart (Table 3). It also loads the compiled
        needed-level kernel (``TERRASTREAM_KERNELS=auto``: numba's import, a compilation the
        first time ever), which ``update`` uses only once loaded. With ``freeze_gc`` it ends
        with :func:`streamer.gcfreeze.freeze_heap`.
        """
        self._check_open("warm_up cannot load for a camera")
        check_camera(camera)
        check_timeout(timeout_s)
        t0 = time.perf_counter()
        levels_kernels.warm_up(self.loader.errors)
        ld = self.loader
        with self._cv:  # (one hold: what the loaders counted so far is the next frame's)
            before = self.totals.loaded_bytes
            discarded_before = self.totals.discarded_bytes
            kept = (ld.frame_realtime, ld.frame_prefetched, ld.frame_discarded, ld.frame_io_s,
                    ld.frame_late)  # fmt: skip
        limit = self.config.wait_timeout_s if timeout_s is None else float(timeout_s)
        start = time.monotonic()
        deadline = start + limit
        with waiting(self.loader, start):  # blocks that gave up are not retried meanwhile
            for _ in range(3):  # errors first, then the levels they ask for, then a last check
                needed = self.planner.needed(camera)
                with self._cv:
                    self._pin_and_queue(needed, camera=camera)
                    self._plans.pending = (camera, None, set(needed))
                self._plans.plan()
                if self.config.workers == 0:
                    self.loader.load_inline(None, deadline)
                    continue
                wait_idle(self.loader, self._raise_background_error, deadline, limit, start)
        with self._cv:  # (one hold: a read arriving now counts in the warm-up or in frame 0)
            # the warm-up's loads and discards are its own; those since the previous frame
            # before it began (a warm-up after frames) stay the next frame's: each is counted
            # once (every load adds to loaded_bytes and to one of the frame counters, every
            # discard to discarded_bytes and frame_discarded; only update() resets them)
            loaded = self.totals.loaded_bytes - before
            discarded = self.totals.discarded_bytes - discarded_before
            (ld.frame_realtime, ld.frame_prefetched, ld.frame_discarded, ld.frame_io_s,
             ld.frame_late) = kept  # fmt: skip
        if self.config.freeze_gc:
            freeze_heap()  # one collection now rather than tens of ms in some later frame
        ms = (time.perf_counter() - t0) * 1000.0
        out = {"ms": ms, "bytes": float(loaded), "discarded_bytes": float(discarded)}
        self.totals.add_warmup(out)
        return out

    def update(self, camera: Camera, dt: float | None = None, *, wait: bool = False) -> Frame:
        """Schedule loads for this camera and report what can be drawn now.

        ``dt`` is the time since the previous pose (default ``1/fps``), used for the velocity
        that stretches the frustum extension: a finite number of seconds >= 0 (0: no velocity;
        NaN, negative or infinite raise :class:`~streamer.errors.CameraError`, a ValueError).
        ``wait=True`` blocks until every visible block holds its needed level or has failed
        ``retries`` times in a row and ``retries`` more times during this wait (bounded by
        ``wait_timeout_s``). With ``warm_start``, the first call runs :meth:`warm_up` first.
        """
        self._check_open("update cannot plan or load a frame")
        check_camera(camera)
        dt = check_dt(dt)
        if not self._updating.acquire(blocking=False):
            raise SessionThreadError(
                "Session.update was called while another thread is inside it; drive a session "
                "from one thread (the renderer's), or give each thread its own session"
            )
        try:
            return self._update(camera, dt, wait)
        finally:
            self._updating.release()

    def _update(self, camera: Camera, dt: float | None, wait: bool) -> Frame:
        """:meth:`update`, its arguments checked, its caller alone inside it."""
        if self.config.warm_start and self.totals.frames == 0 and not self.totals.warmup:
            self.warm_up(camera)
        t0, c0 = time.perf_counter(), time.thread_time()
        self._raise_background_error()
        now = time.monotonic()
        f = self.totals.frames
        self._due = now if self._clock0 is None else self._clock0 + f / self.config.fps
        cfg = self.config
        dt = 1.0 / cfg.fps if dt is None else float(dt)
        velocity = (
            camera.velocity_from(self._prev, dt) if self._prev is not None and dt > 0 else None
        )
        self._prev = camera
        # no lock: the error table is read lock-free
        blocks, levels = self.planner.needed_arrays(camera)
        needed = dict(zip(blocks, levels.tolist(), strict=True))
        todo = to_queue(self.loader, needed, levels)
        need = int(self._cum_array[levels].sum())
        changes = self.cache.pin_changes(needed)  # (only this thread sets the pins)
        with self._cv:  # (one hold: a contended one costs the caller a GIL hand-off too)
            self._pin_and_queue(needed, todo, need, changes, camera=camera)
            start = self._plans.post(camera, velocity, needed.keys())
        if start:
            self._plans.start()
        self.loader.pump()
        update_s, update_cpu = time.perf_counter() - t0, time.thread_time() - c0
        if cfg.workers == 0:
            self._plans.plan()
            self.loader.mark_demand(needed, self._due)
            self.loader.load_inline(cfg.inline_bytes_per_frame)
        t1 = time.perf_counter()
        if wait:
            wait_for(self.loader, cfg, self._raise_background_error, needed, self._due)
            fresh = self.planner.needed(camera)
            if fresh != needed:
                # the errors arrived while waiting: wait for what they say is needed
                with self._cv:
                    self._pin_and_queue(fresh, camera=camera)
                needed, levels, need = fresh, levels_of(fresh), None
                wait_for(self.loader, cfg, self._raise_background_error, needed, self._due)
        t2, c2 = time.perf_counter(), time.thread_time()
        return self._finish_frame(
            camera, needed, levels, need, t2, c2, update_s, update_cpu, t2 - t1
        )

    def _finish_frame(
        self,
        camera: Camera,
        needed: dict[Block, int],
        levels: np.ndarray,
        need: int | None,
        t2: float,
        c2: float,
        update_s: float,
        update_cpu: float,
        wait_s: float,
    ) -> Frame:
        """What this frame may draw, its I/O figures and the caller's timings (``levels``:
        ``needed``'s values as an array; ``need``: their bytes, if summed)."""
        ld, cache = self.loader, self.cache
        level, errors_table, due = cache.level, ld.errors.keys(), self._due
        keys = list(needed)
        hull = None
        if self.config.account_hull and self.stall_set == "triangle":
            hull = self.planner.needed(camera, culling="hull")
        unknown = ld.errors.lookup(keys) < 0  # (the error table is read lock-free)
        with self._cv:  # what changed since the last frame; the pass runs without the lock
            moved = cache.take_level_changes()
        mirror = self._resident
        if moved:
            self._resident_version += 1
        for b, top in moved.items():
            if top < 0:
                mirror.pop(b, None)
            else:
                mirror[b] = top
        seen = mirror.get
        hull_holes = 0
        if hull is not None:
            hull_holes = sum(1 for b in hull if seen(b, -1) < 0)
            hull = any(seen(b, -1) < lv or b not in errors_table for b, lv in hull.items())
        have_list = list(map(seen, keys, repeat(-1)))
        blocks = dict(zip(keys, zip(have_list, needed.values(), strict=True), strict=True))
        shown, self._shown = self._shown, blocks
        # only the blocks whose (resident, needed) changed since the previous frame: for the
        # others the missing levels are marked demanded (with that frame's due time, the
        # first) and the use counted; a level a block lacks cannot have come and gone since
        # (pinned levels are never evicted). Found without the lock, marked under it.
        before = shown.get
        changed = [i for i, (b, st) in enumerate(blocks.items()) if before(b) != st]
        with self._cv:
            for i in changed:
                b = keys[i]
                have, lv = blocks[b]
                if lv <= have:
                    continue
                now = level(b)
                if now > have:  # arrived since the read above: this frame shows it
                    have = have_list[i] = now
                    blocks[b] = (now, lv)
                for lvl in range(have + 1, lv + 1):
                    ld.demanded.add((b, lvl))
                    ld.due.setdefault((b, lvl), due)
            counts = ld.take_counts()
            failed = frozenset(b for b in ld.queue.failed_blocks() if b in needed)
            resident = cache.nbytes - cache.reserved  # levels held, not reads in flight
            errors = self.totals.io_errors
        used = self.totals.used  # (the caller's own: no lock)
        for i in changed:
            have, lv = blocks[keys[i]]
            top = lv if lv < have else have
            if top > used.get(keys[i], -1):
                used[keys[i]] = top
        have = np.array(have_list, dtype=np.int64)
        missing = unknown | (have < levels)
        short = int((levels - have).max()) if len(keys) else 0
        if need is None:
            need = int(self._cum_array[levels].sum())
        t3, c3 = time.perf_counter(), time.thread_time()
        stats = FrameStats(
            frame=self.totals.frames,
            visible_blocks=len(needed),
            prefetch_blocks=self._plans.ring,
            needed_bytes=need,
            realtime_bytes=counts.realtime,
            prefetched_bytes=counts.prefetched,
            io_ms=counts.io_s * 1000.0,
            update_ms=(update_s + t3 - t2) * 1e3,
            update_cpu_ms=(update_cpu + c3 - c2) * 1e3,
            wait_ms=wait_s * 1e3,
            stalled=bool(missing.any()),
            missing_levels=int((levels[missing] - have[missing]).sum()),
            resident_bytes=resident,
            io_errors=errors,
            holes=int((have < 0).sum()),
            failed_blocks=len(failed),
            stall_set=self.stall_set,
            late_bytes=counts.late,
            hull_stalled=hull,
            levels_short=max(0, short),
            discarded_bytes=counts.discarded,
        )
        frame = Frame(camera=camera, blocks=blocks, stats=stats, failed=failed)
        if hull is not None:
            self._hull_hole_frames = (self._hull_hole_frames or 0) + int(hull_holes > 0)
        self._record(frame)
        if counts.unreported and self.config.raise_on_failure:
            b, exc = counts.unreported[0]
            cfg = self.config
            raise LoadError.after_retries(b, exc, cfg.retries, cfg.heal, frame) from exc
        return frame

    def _record(self, frame: Frame) -> None:
        self.totals.add(frame)
        self._peak_frames = max(self._peak_frames, frame.stats.resident_bytes)
        if self._clock0 is None:
            self._clock0 = time.monotonic()  # the frame clock starts once frame 0 is shown

    # -- results ---------------------------------------------------------------------------

    def levels(self, block: Block) -> list[np.ndarray]:
        """Resident decoded levels of a block (for renderers); ``LayoutError`` (a ValueError)
        for a block id outside the store's grid. A closed session still answers with the
        levels it holds (no new one is queued; a read in flight at close may still add one):
        renderers finish drawing its last frame from them (:mod:`render.block_source`). Check
        :attr:`closed` where a closed session's data must not be used."""
        with self._cv:
            return self.cache.levels(block)

    def resident_levels(self) -> dict[Block, int]:
        """The finest resident level of every block holding any, as of the latest
        :meth:`update` (a copy; call it from the caller's thread, as ``update``): what a
        renderer may prepare ahead for blocks not yet in view. After :meth:`close`, as of the
        last ``update`` (it changes no more)."""
        return dict(self._resident)

    def resident_version(self) -> int:
        """A number that changes whenever :meth:`resident_levels` does (no copy made)."""
        return self._resident_version

    def block_side(self, block: Block) -> Side | None:
        """A block's error fields and mask as the loaders read them, and the fields under the
        nodata rule "full" (read-only arrays), or None when not kept
        (:mod:`streamer.blockside`): for renderers, which then read the store.
        ``LayoutError`` (a ValueError) for a block id outside the store's grid. Answered after
        :meth:`close` too, as :meth:`levels`."""
        side = self.loader.side.get(block)
        if side is None:
            self.cache.check_block(block)
        return side

    def summary(self) -> dict[str, Any]:
        """Totals over every frame so far (the ``summary`` object of ``--json``).

        ``peak_resident_bytes`` is the cache's peak of decoded levels at any time (reads that
        arrived after the last frame included); ``peak_resident_bytes_frames`` the largest
        ``FrameStats.resident_bytes`` of the frames (the same quantity, as frames saw it).
        With ``account_hull``, ``stall_frames_hull`` and ``hole_frames_hull`` count the frames
        that lacked a level, or had a block with none, over the frustum hull the renderer draws.
        After :meth:`close` it is the flight's final report (``terrastream stream`` and
        ``flythrough`` take it once the close waited for the reads in flight).
        """
        t = self.totals
        with self._cv:
            used_bytes = sum(self._cum_bytes[top] for top in t.used.values() if top >= 0)
            failed_now = sorted(self.loader.queue.failed_blocks())
            failing = loader_failing(self.loader)
            peak, held = self.cache.peak_nbytes, self.cache.peak_held
        out = t.summary(
            failing=failing,
            used_bytes=used_bytes,
            peak_resident_bytes=peak,
            peak_held_bytes=held,
            budget_bytes=self.cache.budget,
            stall_set=self.stall_set,
            failed_now=failed_now,
        )
        out["peak_resident_bytes_frames"] = self._peak_frames
        out["hole_frames_hull"] = self._hull_hole_frames  # None unless account_hull
        return out


def open_session(
    store: str | TerrainStore,
    *,
    budget_mb: float = 256.0,
    workers: int = 4,
    **config: Any,
) -> Session:
    """Open a streaming session: ``with open_session("s.zarr", budget_mb=256) as s: ...``."""
    return Session(store, SessionConfig(budget_mb=budget_mb, workers=workers, **config))


__all__ = [
    "READ_ERRORS",
    "UNBOUNDED_TAU",
    "BudgetError",
    "Frame",
    "FrameStats",
    "LoadError",
    "Session",
    "SessionClosedError",
    "SessionConfig",
    "open_session",
]
