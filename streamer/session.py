"""Streaming sessions: frustum-extension prefetching into a byte-budgeted cache (Qiu et al. 4).

Each :meth:`Session.update` (the caller's thread) projects the frustum and its extension on the
ground (sets ``M`` and ``N``), picks the level each block needs with the pluggable screen-error
metric, and hands the wants to the loader threads. Loader threads bring blocks up one level at a
time, coarsest first across blocks: visible blocks first, then prefetch blocks by screen error.
Queued work for blocks that left ``N`` is dropped (cancelled). A read that fails is retried with
exponential backoff; after ``retries`` failures the block stays at the level it has and the next
``update`` raises :class:`LoadError` (the session stays usable).

Bytes are decoded level bytes (the source dtype), the quantity held in memory and budgeted.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from streamer.cache import Block, LevelCache
from streamer.camera import Camera
from streamer.errors import BudgetError, LoadError, SessionClosedError, StreamerError
from streamer.frames import Frame, FrameStats, SessionConfig, _Totals
from streamer.frustum import (
    block_edge,
    blocks_meeting,
    extension_triangle,
    frustum_hull,
    view_triangle,
)
from streamer.levels import PatchErrorTable
from streamer.lod import FIELD_FOR_METRIC
from tiler.layout import level_size
from tiler.store import TerrainStore, open_store

log = logging.getLogger(__name__)


PER_BLOCK = 4  # raw levels of one block fetched at once


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
        self.config = config or SessionConfig()
        self.grid = self.store.grid
        self._field_name = FIELD_FOR_METRIC.get(self.config.metric, "qiu")
        itemsize = np.dtype(self.store.meta.dtype).itemsize
        self.level_bytes = [level_size(i) * itemsize for i in range(self.store.k + 1)]
        self.cache = LevelCache(int(self.config.budget_mb * 2**20))
        self._read_hook = read_hook
        idx = self.store.index
        self._exists = idx.exists
        self._zr = np.stack([np.nan_to_num(idx.zmin), np.nan_to_num(idx.zmax)], axis=-1)
        self._zrange = (float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax)))
        self._errors = PatchErrorTable(self.store.k, self.config.patch_log2)
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)  # loaders, and callers waiting for data
        self._sched_cv = threading.Condition(self._lock)  # the scheduler thread
        self._queue: list[tuple[tuple, Block]] = []
        self._fetching: dict[Block, set[int]] = {}  # levels being read (-1: errors)
        self._raw: dict[Block, dict[int, np.ndarray]] = {}  # read, not yet decoded
        self._decoding: set[Block] = set()
        self._demanded: set[tuple[Block, int]] = set()
        self._failures: dict[Block, int] = {}
        self._retry_at: dict[Block, float] = {}
        self._failed: dict[Block, BaseException] = {}
        self._unreported: list[tuple[Block, BaseException]] = []
        self._frame_realtime = 0
        self._frame_prefetched = 0
        self._frame_io_s = 0.0
        self._prev: Camera | None = None
        self._request: tuple | None = None
        self._scheduler_error: BaseException | None = None
        self._prio: dict[Block, tuple] = {}
        self._prefetch_blocks = 0
        self._failures_now: list[tuple[Block, BaseException]] = []
        self._closed = False
        self._stop = False
        self.totals = _Totals()
        self._threads = [
            threading.Thread(target=self._worker, name=f"terrastream-load-{i}", daemon=True)
            for i in range(self.config.workers)
        ]
        if self.config.workers:
            self._threads.append(
                threading.Thread(target=self._scheduler, name="terrastream-schedule", daemon=True)
            )
        for t in self._threads:
            t.start()

    # -- context management ---------------------------------------------------------------

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the loader threads (bounded wait) and release the cache."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            self._stop = True
            self._queue.clear()
            self._cv.notify_all()
            self._sched_cv.notify_all()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(timeout=max(0.0, deadline - time.monotonic()))
        alive = [t.name for t in self._threads if t.is_alive()]
        if alive:
            log.warning("loader threads still running after %.1f s: %s", timeout_s, alive)

    # -- the frame -------------------------------------------------------------------------

    def warm_up(self, camera: Camera, timeout_s: float | None = None) -> dict[str, float]:
        """Before a flight: load everything the plan for ``camera`` wants — the visible levels
        and the prefetch around them — and return ``{"ms", "bytes"}`` spent.

        Without it the first second of a flight stalls while the prefetch ring fills; Qiu et
        al. likewise count the first frame's load apart (Table 3).
        """
        if self._closed:
            raise SessionClosedError("this session is closed")
        t0 = time.perf_counter()
        before = self.totals.loaded_bytes
        limit = timeout_s or self.config.wait_timeout_s
        deadline = time.monotonic() + limit
        for _ in range(3):  # errors first, then the levels they ask for, then a last check
            m = self._visible(camera)
            with self._cv:
                needed = self._needed(camera, m)
                self.cache.set_pins(needed, self.level_bytes)
                self._request = (camera, None, set(m))
            self._schedule_step()
            with self._cv:
                for b in needed:
                    self._push(b, notify=False)
                self._cv.notify_all()
                while self._queue or any(self._fetching.values()) or self._decoding:
                    if self.config.workers == 0:
                        break
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise LoadError(f"warm-up did not finish within {limit:.1f} s")
                    self._cv.wait(timeout=min(left, 0.05))
            if self.config.workers == 0:
                self._load_inline({}, unlimited=True)
        with self._cv:
            self._frame_realtime = self._frame_prefetched = 0
            self._frame_io_s = 0.0
        out = {
            "ms": (time.perf_counter() - t0) * 1000.0,
            "bytes": float(self.totals.loaded_bytes - before),
        }
        self.totals.warmup = out
        return out

    def _visible(self, camera: Camera) -> list[Block]:
        """Blocks meeting the projected frustum (Qiu's triangle or Jung & Han's hull)."""
        cfg = self.config
        poly = view_triangle(camera) if cfg.culling == "qiu" else frustum_hull(camera, self._zrange)
        return [b for b in map(tuple, blocks_meeting(poly, self.grid).tolist()) if self._exists[b]]

    def update(self, camera: Camera, dt: float | None = None, *, wait: bool = False) -> Frame:
        """Schedule loads for this camera and report what can be drawn now.

        ``dt`` is the time since the previous pose (default ``1/fps``), used for the velocity
        that stretches the frustum extension. ``wait=True`` blocks until every visible block
        holds its needed level (bounded by ``wait_timeout_s``).
        """
        if self._closed:
            raise SessionClosedError("this session is closed")
        t0 = time.perf_counter()
        c0 = time.thread_time()
        cfg = self.config
        dt = 1.0 / cfg.fps if dt is None else float(dt)
        velocity = (
            camera.velocity_from(self._prev, dt) if self._prev is not None and dt > 0 else None
        )
        self._prev = camera
        m = self._visible(camera)
        with self._cv:  # one critical section: the error table is shared with the loaders
            self._raise_scheduler_error()
            needed = self._needed(camera, m)
            self.cache.set_pins(needed, self.level_bytes)
            pushed = 0
            for b, lv in needed.items():
                if b not in self._errors or self.cache.level(b) < lv:
                    self._push(b, notify=False)
                    pushed += 1
            self._request = (camera, velocity, set(m))
            # wake only as many loaders as there is new work (each wake-up costs the caller)
            if pushed:
                self._cv.notify(min(pushed, max(1, self.config.workers)))
            self._sched_cv.notify()
        update_s = time.perf_counter() - t0
        update_cpu = time.thread_time() - c0
        if cfg.workers == 0:
            self._schedule_step()
            self._load_inline(needed)
        t1 = time.perf_counter()
        if wait:
            self._wait_for(needed)
            with self._cv:
                fresh = self._needed(camera, list(needed))
            if needed != fresh:
                # the errors arrived while waiting: wait for what they say is needed
                with self._cv:
                    self.cache.set_pins(fresh, self.level_bytes)
                    for b in fresh:
                        self._push(b)
                needed = fresh
                self._wait_for(needed)
        t2, c2 = time.perf_counter(), time.thread_time()
        frame = self._finish_frame(camera, needed)
        # the caller's cost: update work and frame bookkeeping, not the time spent waiting
        t3, c3 = time.perf_counter(), time.thread_time()
        return self._record_frame(frame, update_s + (t3 - t2), update_cpu + (c3 - c2), t2 - t1)

    def _needed(self, camera: Camera, m: list[Block]) -> dict[Block, int]:
        """The level each visible block needs at ``tau`` (the patch level until errors load)."""
        cfg = self.config
        floor = min(cfg.patch_log2, self.store.k)
        needed = {b: floor for b in m}
        have = [b for b in m if b in self._errors]
        if have:
            zr = self._zr[tuple(np.array(have).T)]
            levels, _ = self._errors.needed_levels(self.grid, have, camera, cfg.tau, cfg.metric, zr)
            needed.update(zip(have, levels.tolist(), strict=True))
        return needed

    def _schedule_step(self) -> None:
        """Prefetch planning for the latest frame: the blocks ``N`` of the frustum extension, of
        this camera and of the camera ``horizon_s`` ahead along its velocity, and the level each
        would need at ``tau * lookahead`` from either pose; then the work queue is rebuilt."""
        with self._cv:
            req, self._request = self._request, None
        if req is None:
            return
        camera, velocity, visible = req
        cfg = self.config
        n = set(visible)
        poses = [camera]
        if cfg.prefetch:
            v = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64)
            if cfg.horizon_s > 0 and np.any(v):
                ahead_pos = np.asarray(camera.position, dtype=np.float64) + v * cfg.horizon_s
                poses.append(replace(camera, position=tuple(ahead_pos.tolist())))
            edge = block_edge(self.grid) if cfg.extension_L is None else cfg.extension_L
            for cam in poses:
                ext = extension_triangle(cam, edge, velocity=v, fps=cfg.fps)
                n.update(
                    b
                    for b in map(tuple, blocks_meeting(ext, self.grid).tolist())
                    if self._exists[b]
                )
        blocks = sorted(n)
        wants: dict[Block, tuple[int, float]] = {b: (0, 0.0) for b in blocks}
        have = [b for b in blocks if b in self._errors]
        if have:
            zr = self._zr[tuple(np.array(have).T)]
            tau = cfg.tau * (cfg.lookahead if cfg.prefetch else 1.0)
            levels = np.zeros(len(have), dtype=np.int64)
            rho = np.zeros(len(have))
            for cam in poses:
                with self._cv:
                    lv, r = self._errors.needed_levels(self.grid, have, cam, tau, cfg.metric, zr)
                np.maximum(levels, lv, out=levels)
                np.maximum(rho, r, out=rho)
            for b, lv, r in zip(have, levels.tolist(), rho.tolist(), strict=True):
                wants[b] = (lv, r)
        with self._cv:
            self.cache.set_prefetch(wants)
            if cfg.linger_s is not None:
                self.cache.trim(int(cfg.linger_s * cfg.fps))
            self._prefetch_blocks = len(n) - len(visible)
            self._reschedule()

    def _scheduler(self) -> None:
        while True:
            with self._cv:
                while self._request is None and not self._stop:
                    self._sched_cv.wait(timeout=0.1)
                if self._stop:
                    return
            try:
                self._schedule_step()
            except Exception as exc:  # noqa: BLE001 - surfaced by the next update()
                with self._cv:
                    self._scheduler_error = exc

    def _raise_scheduler_error(self) -> None:
        if self._scheduler_error is not None:
            exc, self._scheduler_error = self._scheduler_error, None
            raise StreamerError(f"prefetch planning failed: {exc}") from exc

    def _key(self, b: Block, level: int | None = None) -> tuple:
        """Queue order: errors first, then pinned levels, coarse before fine, by screen error."""
        want, pin = self.cache.want(b)
        nxt = self.cache.level(b) + 1 if level is None else level
        _, _, _, prio = self._prio.get(b, (b, want, pin, 0.0))
        return (0 if b not in self._errors else 1, 0 if nxt <= pin else 1, nxt, -prio, b)

    def _push(self, b: Block, level: int | None = None, *, notify: bool = True) -> None:
        """Queue ``b`` for its next load (caller holds the lock)."""
        if b in self._failed:
            return
        heapq.heappush(self._queue, (self._key(b, level), b))
        if notify:
            self._cv.notify_all()

    def _reschedule(self) -> None:
        """Rebuild the work queue from the cache's wants (caller holds the lock)."""
        before = {b for _, b in self._queue}
        self._queue = []
        self._prio = {}
        now = time.monotonic()
        for b, want, pin, prio in self.cache.wanted():
            self._prio[b] = (b, want, pin, prio)
            if b in self._failed or (self.cache.level(b) >= want and b in self._errors):
                continue
            key = self._key(b)
            if self._retry_at.get(b, 0.0) > now:
                key = (2, *key[1:])
            self._queue.append((key, b))
        heapq.heapify(self._queue)
        self.totals.cancelled += len(before - {b for _, b in self._queue})
        self._cv.notify_all()

    # -- loading ---------------------------------------------------------------------------

    def _fetchable(self, b: Block) -> int | None:
        """Next level of ``b`` to fetch (-1: its errors), or None (caller holds the lock).

        Raw levels of one block are fetched concurrently (up to ``PER_BLOCK`` at a time) and
        decoded in order, so a block needing several levels pays the store latency once.
        """
        if b in self._failed or self._retry_at.get(b, 0.0) > time.monotonic():
            return None
        busy = self._fetching.get(b, set())
        if b not in self._errors:
            return None if -1 in busy else -1
        want, _pin = self.cache.want(b)
        pending = self._raw.get(b, {})
        if len(busy) >= PER_BLOCK:
            return None
        for level in range(self.cache.level(b) + 1, min(want, self.store.k) + 1):
            if level not in busy and level not in pending:
                return level
        return None

    def _next_job(self) -> tuple[Block, int] | None:
        """Pop the most urgent ``(block, level)`` to fetch (caller holds the lock)."""
        backing_off = []
        job = None
        now = time.monotonic()
        while self._queue:
            key, b = heapq.heappop(self._queue)
            if self._retry_at.get(b, 0.0) > now and b not in self._failed:
                backing_off.append((key, b))
                continue
            level = self._fetchable(b)
            if level is None:
                continue  # re-pushed when its fetches finish, or by the next schedule
            if level >= 0 and not self.cache.reserve(b, self.level_bytes[level]):
                continue  # no room: pinned data fills the budget
            self._fetching.setdefault(b, set()).add(level)
            more = self._fetchable(b)
            if more is not None:
                self._push(b, more)  # its next level can be fetched by another worker
            job = (b, level)
            break
        for item in backing_off:
            heapq.heappush(self._queue, item)
        return job

    def _fetch(self, b: Block, level: int) -> None:
        """Read errors or one raw level of ``b`` (no lock held), then decode what is ready."""
        t0 = time.perf_counter()
        try:
            if self.config.latency_ms:
                time.sleep(self.config.latency_ms / 1000.0)
            if self._read_hook is not None:
                self._read_hook(b, level)
            if level < 0:
                data = self.store.read_errors(b)[self._field_name]
            else:
                data = self.store.read_level_raw(b, level)
        except Exception as exc:  # noqa: BLE001 - any read failure is counted and retried
            with self._cv:
                if level >= 0:
                    self.cache.release(self.level_bytes[level])
                self.totals.io_errors += 1
                count = self._failures.get(b, 0) + 1
                self._failures[b] = count
                if count >= self.config.retries:
                    self._failed[b] = exc
                    self._unreported.append((b, exc))
                else:
                    self._retry_at[b] = time.monotonic() + self.config.backoff_s * 2 ** (count - 1)
                self._frame_io_s += time.perf_counter() - t0
            log.warning("reading block %s level %d failed (%d): %s", b, level, count, exc)
            return
        with self._cv:
            self._failures.pop(b, None)
            self._retry_at.pop(b, None)
            self._frame_io_s += time.perf_counter() - t0
            if level < 0:
                self._errors.add(b, data)
                return
            self._raw.setdefault(b, {})[level] = data
            if b in self._decoding:
                return
            self._decoding.add(b)
        try:
            self._decode_ready(b)
        finally:
            with self._cv:
                self._decoding.discard(b)

    def _decode_ready(self, b: Block) -> None:
        """Decode ``b``'s fetched levels that follow its resident ones, in order."""
        while True:
            t0 = time.perf_counter()
            with self._cv:
                nxt = self.cache.level(b) + 1
                raw = self._raw.get(b, {}).pop(nxt, None)
                if raw is None:
                    return
                levels = self.cache.levels(b)
            values = self.store.to_heights(self.store.decode_next(_storage(self, levels), raw))
            with self._cv:
                self._frame_io_s += time.perf_counter() - t0
                nbytes = int(values.nbytes)
                if self.cache.level(b) != nxt - 1 or not self.cache.add_level(
                    b, nxt, values, reserved=True
                ):
                    self._drop_raw(b)  # evicted or unwanted meanwhile
                    return
                self.totals.loaded_bytes += nbytes
                if (b, nxt) in self._demanded:
                    self._frame_realtime += nbytes
                else:
                    self._frame_prefetched += nbytes
                self._cv.notify_all()

    def _drop_raw(self, b: Block) -> None:
        """Forget fetched but undecodable levels of ``b`` (caller holds the lock)."""
        for level in self._raw.pop(b, {}):
            self.cache.release(self.level_bytes[level])

    def _worker(self) -> None:
        while True:
            with self._cv:
                job = None
                while not self._stop:
                    job = self._next_job()
                    if job is not None:
                        break
                    self._cv.wait(timeout=0.05)
                if self._stop:
                    if job is not None and job[1] >= 0:
                        self.cache.release(self.level_bytes[job[1]])
                    return
            self._run_job(job)

    def _run_job(self, job: tuple[Block, int]) -> None:
        b, level = job
        try:
            self._fetch(b, level)
        finally:
            with self._cv:
                self._fetching.get(b, set()).discard(level)
                self._requeue(b)

    def _requeue(self, b: Block) -> None:
        """Put ``b`` back in the queue if it still wants more (caller holds the lock)."""
        backing_off = b not in self._failed and self._retry_at.get(b, 0.0) > time.monotonic()
        if backing_off or self._fetchable(b) is not None:
            self._push(b)
        elif not self._fetching.get(b) and b in self._raw and b not in self._decoding:
            self._drop_raw(b)  # levels fetched beyond a gap that will not be filled

    def _load_inline(self, needed: dict[Block, int], unlimited: bool = False) -> None:
        """``workers=0``: do this frame's loads now, up to the per-frame allowance."""
        allowance = None if unlimited else self.config.inline_bytes_per_frame
        spent = 0
        self._mark_demand(needed)
        while allowance is None or spent < allowance:
            with self._cv:
                job = self._next_job()
            if job is None:
                break
            before = self.totals.loaded_bytes
            self._run_job(job)
            spent += self.totals.loaded_bytes - before

    def _missing(self, needed: dict[Block, int]) -> list[tuple[Block, int]]:
        return [
            (b, lv) for b, lv in needed.items() if self.cache.level(b) < lv or b not in self._errors
        ]

    def _mark_demand(self, needed: dict[Block, int]) -> None:
        with self._cv:
            for b, lv in needed.items():
                for level in range(self.cache.level(b) + 1, lv + 1):
                    self._demanded.add((b, level))

    def _wait_for(self, needed: dict[Block, int]) -> float:
        t0 = time.perf_counter()
        self._mark_demand(needed)
        deadline = time.monotonic() + self.config.wait_timeout_s
        with self._cv:
            while self._missing(needed) and not any(b in self._failed for b in needed):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LoadError(
                        f"{len(self._missing(needed))} visible block level(s) did not load within "
                        f"{self.config.wait_timeout_s:.1f} s"
                    )
                if self.config.workers == 0:
                    break
                self._cv.wait(timeout=min(left, 0.05))
        if self.config.workers == 0 and self._missing(needed):
            self._load_inline(needed, unlimited=True)
        return time.perf_counter() - t0

    def _finish_frame(self, camera: Camera, needed: dict[Block, int]) -> Frame:
        """What this frame may draw and its I/O figures (timings are filled in afterwards)."""
        with self._cv:
            missing = self._missing(needed)
            for b, lv in missing:
                for level in range(self.cache.level(b) + 1, lv + 1):
                    self._demanded.add((b, level))
            blocks = {b: (self.cache.level(b), lv) for b, lv in needed.items()}
            used = self.totals.used
            for b, (have, lv) in blocks.items():
                top = min(lv, have)
                if top > used.get(b, -1):
                    used[b] = top
            realtime, prefetched = self._frame_realtime, self._frame_prefetched
            io_s = self._frame_io_s
            self._frame_realtime = self._frame_prefetched = 0
            self._frame_io_s = 0.0
            self._failures_now, self._unreported = self._unreported, []
            resident = self.cache.nbytes
            errors = self.totals.io_errors
        stats = FrameStats(
            frame=self.totals.frames,
            visible_blocks=len(needed),
            prefetch_blocks=self._prefetch_blocks,
            needed_bytes=sum(sum(self.level_bytes[: lv + 1]) for lv in needed.values()),
            realtime_bytes=realtime,
            prefetched_bytes=prefetched,
            io_ms=io_s * 1000.0,
            update_ms=0.0,
            update_cpu_ms=0.0,
            wait_ms=0.0,
            stalled=bool(missing),
            missing_levels=sum(lv - max(blocks[b][0], -1) for b, lv in missing),
            resident_bytes=resident,
            io_errors=errors,
        )
        return Frame(camera=camera, blocks=blocks, stats=stats)

    def _record_frame(self, frame: Frame, wall_s: float, cpu_s: float, wait_s: float) -> Frame:
        """Fill in the caller-thread timings, add the frame to the totals, report failures."""
        st = replace(
            frame.stats, update_ms=wall_s * 1e3, update_cpu_ms=cpu_s * 1e3, wait_ms=wait_s * 1e3
        )
        object.__setattr__(frame, "stats", st)
        t = self.totals
        t.needed_bytes += st.needed_bytes
        t.realtime_bytes += st.realtime_bytes
        if t.frames > 0:
            t.realtime_bytes_after_first += st.realtime_bytes
        t.prefetched_bytes += st.prefetched_bytes
        t.stall_frames += int(st.stalled)
        t.max_update_ms = max(t.max_update_ms, st.update_ms)
        t.max_update_cpu_ms = max(t.max_update_cpu_ms, st.update_cpu_ms)
        t.frames += 1
        failures, self._failures_now = self._failures_now, []
        if failures:
            b, exc = failures[0]
            raise LoadError(
                f"block {b} could not be read after {self.config.retries} tries: {exc}; "
                "it stays at the level it has"
            ) from exc
        return frame

    # -- results ---------------------------------------------------------------------------

    def levels(self, block: Block) -> list[np.ndarray]:
        """Resident decoded levels of a block (for renderers)."""
        with self._cv:
            return self.cache.levels(block)

    def summary(self) -> dict[str, Any]:
        """Totals over every frame so far (the ``summary`` object of ``--json``)."""
        t = self.totals
        with self._cv:
            used_bytes = sum(sum(self.level_bytes[: top + 1]) for top in t.used.values())
        return {
            "frames": t.frames,
            "stall_frames": t.stall_frames,
            "needed_bytes": t.needed_bytes,
            "realtime_bytes": t.realtime_bytes,
            "realtime_bytes_after_first_frame": t.realtime_bytes_after_first,
            "prefetched_bytes": t.prefetched_bytes,
            "loaded_bytes": t.loaded_bytes,
            "used_bytes": used_bytes,
            "wasted_bytes": max(0, t.loaded_bytes - used_bytes),
            "peak_resident_bytes": self.cache.peak_nbytes,
            "budget_bytes": self.cache.budget,
            "max_update_ms": t.max_update_ms,
            "max_update_cpu_ms": t.max_update_cpu_ms,
            "io_errors": t.io_errors,
            "cancelled_loads": t.cancelled,
            "warmup_ms": t.warmup.get("ms", 0.0),
            "warmup_bytes": int(t.warmup.get("bytes", 0)),
        }


def _storage(session: Session, levels: list[np.ndarray]) -> list[np.ndarray]:
    """Decoded heights back to the store's value units (quantised stores keep integers)."""
    p = session.store.meta.precision
    if not p:
        return levels
    return [np.rint(v.astype(np.float64) / p).astype(np.int32) for v in levels]


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
    "BudgetError",
    "Frame",
    "FrameStats",
    "LoadError",
    "Session",
    "SessionClosedError",
    "SessionConfig",
    "open_session",
]
