"""Loading block levels on a named thread pool into the byte-budgeted cache.

A :class:`Loader` owns the shared state of a session (cache, queue, error table, counters) and
its lock. Work is *pumped*: whenever there may be something to do (an update, a finished read,
a waiter waking for a retry) up to ``workers`` jobs are taken from the queue and submitted to a
:class:`streamer.pool.DaemonPool` (daemon threads ``terrastream-load_N``: a read a server never
answers does not hold the interpreter at exit); a completion callback records the outcome and
pumps again. Nothing polls.

A job reads one thing of one block with no lock held: its error field (level ``-1``) or one raw
level (up to ``PER_BLOCK`` levels of a block in flight at once; under a level-by-level scheme
such as ``"qiu"`` one level, the next only once the previous is decoded), then decodes the levels
that follow the resident ones, in order, also without the lock. The lock guards only bookkeeping:
dict and heap updates, never a read, a decode or a plan.

Only the errors a read can raise are counted as read failures (:data:`READ_ERRORS`): ``OSError``
(which includes the tiler's ``StoreError`` family and timeouts) and zarr's own errors. Anything
else is a bug: it is kept and re-raised by the session's next ``update``. A store replaced or
rewritten under the session (:class:`StoreChangedError`) is neither: it is final (``fatal``), no
read is retried or started after it, and every later ``update`` raises it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from typing import NamedTuple

import numpy as np
import zarr.errors

from streamer.blockside import BlockSide, Side, side_bytes
from streamer.cache import Block, LevelCache
from streamer.frames import SessionConfig, Totals
from streamer.levels import PatchErrorTable
from streamer.loadqueue import LoadQueue
from streamer.nodata import (
    has_boundary,
    mixed_nodes,
    pack_mixed,
    raise_all,
    read_side,
    rule_errors_of,
)
from streamer.pool import DaemonPool
from tiler.errors import (
    StoreChangedError,
    StoreCorruptError,
    StoreError,
)
from tiler.store import TerrainStore

log = logging.getLogger(__name__)

#: the name prefix of every loader thread (``terrastream-load_N``)
THREAD_PREFIX = "terrastream-load"


def threads_alive() -> list[str]:
    """Names of loader threads still running in this process (of any session), e.g. reads a
    server never answered after their session closed; they end when the read times out."""
    return [t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX)]


PER_BLOCK = 4  # raw levels of one block fetched at once

#: Errors a block read can raise; anything else surfaces as a bug.
READ_ERRORS: tuple[type[BaseException], ...] = (OSError, StoreError, zarr.errors.BaseZarrError)

Job = tuple[Block, int]


class FrameCounts(NamedTuple):
    """What the loaders counted since the previous frame (:meth:`Loader.take_counts`): the
    decoded bytes loaded in time (real-time) and ahead (prefetched), the I/O seconds, the bytes
    that came late, the bytes read but discarded on arrival, and the failures not yet
    reported."""

    realtime: int
    prefetched: int
    io_s: float
    late: int
    discarded: int
    unreported: list[tuple[Block, BaseException]]


class Loader:
    """Shared loading state, the work queue and the pool that drains it (see module doc)."""

    def __init__(
        self,
        store: TerrainStore,
        config: SessionConfig,
        level_bytes: list[int],
        field_name: str,
        read_hook: Callable[[Block, int], None] | None = None,
    ) -> None:
        self.store = store
        self.config = config
        self.level_bytes = level_bytes
        self.field_name = field_name
        self.read_hook = read_hook
        self.cache = LevelCache(int(config.budget_mb * 2**20), store.grid.shape)
        #: the error fields and masks the loaders read, for the session's renderer
        self.side = BlockSide(side_bytes(int(config.budget_mb * 2**20)))
        self.errors = PatchErrorTable(store.k, config.patch_log2, gaps=config.nodata == "gap")
        self.queue = LoadQueue(
            retries=config.retries,
            backoff_s=config.backoff_s,
            max_backoff_s=config.max_backoff_s,
            heal=config.heal,
        )
        self.totals = Totals()
        self.cv = threading.Condition(threading.Lock())
        self.fetching: dict[Block, set[int]] = {}  # levels being read (-1: errors)
        self.raw: dict[Block, dict[int, np.ndarray]] = {}  # read, not yet decoded
        self.decoding: set[Block] = set()
        self.probes: set[Job] = set()  # reads running of blocks failed when they started
        # the levels a frame lacked, each until it arrives (then a later reload of it is
        # classified afresh) or the camera moves on (:meth:`forget_steps`), and the due time
        # of the first frame that lacked it: the same keys
        self.demanded: set[tuple[Block, int]] = set()
        self.due: dict[tuple[Block, int], float] = {}
        self.ever_loaded: set[tuple[Block, int]] = set()  # (block, level) loaded at least once
        self.frame_late = 0
        self.unreported: list[tuple[Block, BaseException]] = []
        self.last_error: dict[Block, BaseException] = {}  # blocks whose latest read failed
        self.latest_error: BaseException | None = None  # the latest read error of any block
        self.failed_level: dict[Block, int] = {}  # the level of each block's last failed read
        self.frame_realtime = 0
        self.frame_prefetched = 0
        self.frame_io_s = 0.0
        self.frame_discarded = 0  # bytes read but discarded on arrival (:meth:`_discard`)
        self.bug: BaseException | None = None
        self.fatal: StoreChangedError | None = None  # the store changed under the session
        self.closed = False
        self._in_flight = 0
        self._pool = DaemonPool(config.workers, THREAD_PREFIX) if config.workers else None

    # -- queue keys ------------------------------------------------------------------------

    def key(self, b: Block, level: int | None = None) -> tuple:
        """Queue order: errors first, then pinned levels, coarse before fine, by screen error
        (caller holds the lock)."""
        _want, pin, prio = self.cache.want_priority(b)
        nxt = self.cache.level(b) + 1 if level is None else level
        return (0 if b not in self.errors else 1, 0 if nxt <= pin else 1, nxt, -prio, b)

    def push(self, b: Block, level: int | None = None) -> None:
        """Queue ``b`` for its next load (caller holds the lock)."""
        self.queue.push(b, self.key(b, level))

    def reschedule(self) -> None:
        """Rebuild the queue from the cache's wants (caller holds the lock)."""
        for _ in self.reschedule_steps():
            pass

    def reschedule_steps(self, chunk: int = 64) -> Iterator[None]:
        """:meth:`reschedule` in steps of at most ``chunk`` blocks; the caller holds the lock
        during each step and may release it between them. Keys computed in an earlier step
        may be slightly stale by the swap; a job is re-checked when it is taken. The queue
        holds the blocks that want a level they do not hold (``LevelCache.short_steps``): a
        block's errors come before any of its levels (:meth:`fetchable`), so a block without
        them is one of those. Demands of levels no longer wanted are forgotten first
        (:meth:`forget_steps`)."""
        yield from self.forget_steps(chunk)
        items = []
        errors, level = self.errors, self.cache.level
        for part in self.cache.short_steps(chunk):
            for b, _want, pin, prio in part:  # (:meth:`key`, from the entry's values read)
                nxt = level(b) + 1
                key = (0 if b not in errors else 1, 0 if nxt <= pin else 1, nxt, -prio, b)
                items.append((key, b))
            yield
        yield from self.queue.rebuild_steps(items, time.monotonic(), chunk)
        self.totals.cancelled = self.queue.cancelled

    def forget_steps(self, chunk: int = 64) -> Iterator[None]:
        """Forget the demands (and due times) of levels no longer wanted (the plan's wants and
        the pins; the pins alone with ``prefetch`` off, as :meth:`fetchable`), in steps of at
        most ``chunk`` demands (the caller holds the lock during each). The camera moved on
        before they were read: a later read of such a level, ahead of need, is prefetched and
        not late against a frame long gone. Kept: a level being read or decoded (:meth:`reading`:
        bytes read because a frame lacked them stay real-time) and the levels of a failing
        block (:meth:`failing`: still a block a frame needed, ``loadreport.failing``). Run by
        the planning thread after it applied a plan's wants (:meth:`reschedule_steps`), where
        wants are lowered; pinned levels are always wanted, so a frame's demands stay while
        it pins them."""
        keys = list(self.demanded)
        want, prefetch = self.cache.want, self.config.prefetch
        for i in range(0, len(keys), chunk):
            for key in keys[i : i + chunk]:
                b, level = key
                w, pin = want(b)
                if (w if prefetch else pin) >= level or self.reading(b, level):
                    continue
                if self.failing(b) or key not in self.demanded:
                    continue
                self.demanded.discard(key)
                self.due.pop(key, None)
            yield

    def reading(self, b: Block, level: int) -> bool:
        """Whether ``level`` of ``b`` is being read or decoded (caller holds the lock)."""
        return (
            level in self.fetching.get(b, ())
            or level in self.raw.get(b, ())
            or (b in self.decoding)
        )

    def failing(self, b: Block) -> bool:
        """Whether ``b``'s latest read failed or it is failed (caller holds the lock)."""
        return b in self.last_error or self.queue.is_failed(b)

    # -- taking jobs -----------------------------------------------------------------------

    def fetchable(self, b: Block) -> int | None:
        """Next level of ``b`` to fetch (-1: its errors), or None (caller holds the lock).
        With ``prefetch`` off only what a frame pinned: the plan's wants above the pins are
        levels no frame asked for yet (the level the view needs of a block pinned at the patch
        level before its errors arrived, found by the planning thread first), read ahead."""
        want, pin = self.cache.want(b)
        if not self.config.prefetch:
            if pin < 0:
                return None  # no frame needs it (not even its errors)
            want = pin
        busy = self.fetching.get(b, set())
        if b not in self.errors:
            return None if -1 in busy else -1
        pending = self.raw.get(b, {})
        if not self.config.concurrent_levels:  # level by level: nothing of b under way
            if busy or pending or b in self.decoding:
                return None
        elif len(busy) >= PER_BLOCK:
            return None
        for level in range(self.cache.level(b) + 1, min(want, self.store.k) + 1):
            if level not in busy and level not in pending:
                return level
        return None

    def _take(self, b: Block) -> int | None:
        level = self.fetchable(b)
        if level is None:
            return None
        nbytes = self.level_bytes[level] if level >= 0 else 0
        if level >= 0 and not (self.cache.room_for(b, nbytes) and self.cache.reserve(b, nbytes)):
            return None  # no room: pinned or more important prefetched data fills the budget
        self.fetching.setdefault(b, set()).add(level)
        more = self.fetchable(b)
        if more is not None:
            self.push(b, more)  # its next level can be fetched by another job
        return level

    def next_job(
        self, probe: bool = True, take: Callable[[Block], int | None] | None = None
    ) -> Job | None:
        """Pop the most urgent ``(block, level)`` to fetch (caller holds the lock); a failed
        block's retry only if ``probe`` and none runs (``LoadQueue.pop``); ``take``: instead
        of :meth:`_take` (None drops the block from the queue)."""
        take = take or self._take
        job = self.queue.pop(time.monotonic(), take, probe=probe and not self.probes)
        if job is not None and self.queue.is_failed(job[0]):
            self.probes.add(job)  # a retry of a failed block: see LoadQueue.pop
        return job

    def pump(self) -> None:
        """Submit jobs while workers are free. Jobs are taken under the lock (heap pops and
        reservations only); submitting and attaching the completion callback happen after it
        is released, so a callback can never run while this thread holds the lock."""
        if self._pool is None:
            return
        jobs = []
        # after a bug no new job starts (the failing block would only be retried); the
        # session re-raises the bug and clears it, and pumping resumes. After a store change
        # nothing starts again. One job per hold of the lock: a take that must evict walks
        # the cache, and four in a row held the lock the caller waits on for ~1 ms.
        while self._in_flight < self.config.workers:  # (read without the lock: a worker
            with self.cv:  # that frees up pumps itself, see _done)
                job = self._take_job()
            if job is None:
                break
            jobs.append(job)
        self._submit(jobs)

    def _take_job(self) -> Job | None:
        """The next job if a worker is free and jobs may start, counted in flight (caller
        holds the lock)."""
        if (
            self.closed
            or self.bug is not None
            or self.fatal is not None
            or self._in_flight >= self.config.workers
        ):
            return None
        job = self.next_job()
        if job is not None:
            self._in_flight += 1
        return job

    def _submit(self, jobs: list[Job]) -> None:
        """Run ``jobs`` (taken by :meth:`_take_job`) on the pool (no lock held)."""
        assert self._pool is not None
        for k, job in enumerate(jobs):
            try:
                fut = self._pool.submit(self.run_job, job)
            except RuntimeError:  # the pool shut down meanwhile: give the jobs back
                with self.cv:
                    for j in jobs[k:]:
                        self._in_flight -= 1
                        self._unreserve(j)
                return
            fut.add_done_callback(self._done)

    def _done(self, fut: Future) -> None:
        exc = None if fut.cancelled() else fut.exception()
        with self.cv:  # the worker's next job taken in the same hold
            self._in_flight -= 1
            if exc is not None and self.bug is None:
                self.bug = exc  # not a read error: re-raised by the next update
            self.cv.notify_all()
            job = self._take_job() if exc is None else None
        if job is not None:
            self._submit([job])
            self.pump()

    def _unreserve(self, job: Job) -> None:
        b, level = job
        self.fetching.get(b, set()).discard(level)
        self.probes.discard(job)
        if level >= 0:
            self.cache.release(self.level_bytes[level])

    # -- running a job ---------------------------------------------------------------------

    def run_job(self, job: Job) -> None:
        """Fetch ``job`` and decode what became decodable, then requeue its block."""
        b, level = job
        try:
            self._fetch(b, level)
        except Exception as exc:
            what = "its errors" if level < 0 else f"level {level}"
            exc.add_note(f"raised by a terrastream loader thread reading {what} of block {b}")
            raise
        finally:
            with self.cv:
                self.fetching.get(b, set()).discard(level)
                self.probes.discard(job)
                self._requeue(b)

    def _fetch(self, b: Block, level: int) -> None:
        t0 = time.perf_counter()
        try:
            if self.config.latency_ms:
                time.sleep(self.config.latency_ms / 1000.0)
            if self.read_hook is not None:
                self.read_hook(b, level)
            data = self.read_errors(b) if level < 0 else self.store.read_level_raw(b, level)
        except READ_ERRORS as exc:
            with self.cv:
                if level >= 0:
                    self.cache.release(self.level_bytes[level])
                self.totals.io_errors += 1
                if isinstance(exc, StoreChangedError):  # final: not a block's failure to retry
                    self.fatal = self.fatal or exc
                    self.latest_error = exc
                    self.cv.notify_all()
                    return
                was_failed = self.queue.is_failed(b)
                count = self.queue.failed_read(b, time.monotonic())
                self.last_error[b] = exc
                self.failed_level[b] = level
                self.latest_error = exc
                if self.queue.is_failed(b) and not was_failed:
                    self.unreported.append((b, exc))
                self.frame_io_s += time.perf_counter() - t0
            # after close() (which stops waiting for reads in flight after its timeout) a
            # read that then fails concerns no frame: said at debug, not as a warning to a
            # user whose session or command has already ended
            say = log.debug if self.closed else log.warning
            say("reading block %s level %d failed (%d): %s", b, level, count, exc)
            return
        if level < 0:
            self.errors.add(b, *data)  # the table has its own writer lock; readers need none
        with self.cv:
            self.queue.succeeded(b)
            healed = self.last_error.pop(b, None)
            if self.failed_level.pop(b, None) != level:
                healed = None  # (another level failed: this read says nothing of its data)
            self.frame_io_s += time.perf_counter() - t0
            if level < 0:
                self.cv.notify_all()
                decode = False
            else:
                self.raw.setdefault(b, {})[level] = data
                decode = b not in self.decoding
                if decode:
                    self.decoding.add(b)
        if healed is not None:  # (a damage message above was a transfer's, not the store's)
            log.warning(
                "block %s level %d read correctly after a failed read of it (%s): its data in "
                "the store is intact, the failure was in transfer",
                b,
                level,
                healed,
            )
        if not decode:
            return
        try:
            self._decode_ready(b)
        finally:
            with self.cv:
                self.decoding.discard(b)

    def read_errors(self, b: Block) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
        """The block's error field and gap widths under the session's nodata rule
        (:func:`streamer.nodata.rule_errors`); the fields and mask read are kept in
        :attr:`side`. A chunk that zarr or its codecs cannot decode raises
        ``ValueError``/``RuntimeError`` there; like ``TerrainStore.read_level_raw`` does for
        levels, that becomes a ``StoreCorruptError`` (a read error), here at the store calls
        only, so the same types raised anywhere else still surface as bugs."""
        try:
            errors, mask = read_side(self.store, b)
        except (ValueError, RuntimeError) as exc:
            if isinstance(exc, READ_ERRORS):
                raise
            raise StoreCorruptError(
                f"cannot read the {self.field_name!r} errors of block {b} from "
                f"{self.store.url!r}: {exc}"
            ) from exc
        k, g = self.store.k, self.store.grid
        mixed = mixed_nodes(mask, k) if has_boundary(mask) else None
        packed = None if mixed is None else pack_mixed(mixed, k)
        self.side.put(b, Side(errors, mask, raise_all(errors, mask, k, mixed), packed))
        # "full": mask boundaries raised so nodata is refined at every tau; "gap": the
        # stored errors and the mixed cells' widths (streamer.nodata)
        field = errors[self.field_name]
        return rule_errors_of(field, mask, k, g.dx, g.dy, self.config.nodata, mixed)

    def _decode_ready(self, b: Block) -> None:
        """Decode ``b``'s fetched levels that follow its resident ones, in order (no lock held
        while decoding)."""
        while True:
            t0 = time.perf_counter()
            with self.cv:
                nxt = self.cache.level(b) + 1
                raw = self.raw.get(b, {}).pop(nxt, None)
                if raw is None:
                    return
                levels = self.cache.levels(b)
            try:
                decoded = self.store.decode_next(_storage(self.store, levels), raw)
                values = self.store.to_heights(decoded)
            except BaseException:  # a bug, raised on (see run_job): nxt was read all the same
                with self.cv:
                    self.cache.release(self.level_bytes[nxt])
                    self._discard(self.level_bytes[nxt])
                raise
            with self.cv:
                self.frame_io_s += time.perf_counter() - t0
                nbytes = int(values.nbytes)
                evicted = self.cache.level(b) != nxt - 1  # (add_level releases it otherwise)
                if evicted:
                    self.cache.release(self.level_bytes[nxt])
                if evicted or not self.cache.add_level(b, nxt, values, reserved=True):
                    self._discard(nbytes)
                    self._drop_raw(b)  # evicted or unwanted meanwhile
                    return
                self.totals.loaded_bytes += nbytes
                if (b, nxt) in self.ever_loaded:  # evicted since it was last loaded
                    self.totals.reloaded_bytes += nbytes
                    self.totals.reloaded_levels += 1
                else:
                    self.ever_loaded.add((b, nxt))
                due = self.due.pop((b, nxt), None)
                if due is not None and time.monotonic() > due:
                    self.frame_late += nbytes
                # real-time: a level a frame lacked since it last arrived, or one the frame
                # being made pins (it needs it; a read that came back before that frame was
                # finished counted as prefetched, prefetch off too, as the frame had not
                # marked it yet). With prefetch off only pinned levels are read (fetchable):
                # all real-time. A demand is met once its level arrives (its due time went
                # above): a reload of the level after an eviction, read ahead, is prefetched
                # (it stayed real-time for good, and the set grew through the flight). A level
                # that never arrives (a failing read) stays demanded: loadreport.failing; one
                # no longer wanted, not read, is forgotten (forget_steps)
                demanded = (b, nxt) in self.demanded
                self.demanded.discard((b, nxt))
                if demanded or self.cache.want(b)[1] >= nxt:
                    self.frame_realtime += nbytes
                else:
                    self.frame_prefetched += nbytes
                self.cv.notify_all()

    def _drop_raw(self, b: Block) -> None:
        """Forget fetched but undecodable levels of ``b``, counted as discarded (caller holds
        the lock)."""
        for level in self.raw.pop(b, {}):
            self.cache.release(self.level_bytes[level])
            self._discard(self.level_bytes[level])

    def _discard(self, nbytes: int) -> None:
        """Count a level read from the store but thrown away, never cached (caller holds the
        lock): ``Totals.discarded_bytes``, so that the bytes read are ``loaded_bytes`` plus
        ``discarded_bytes``, and the next frame's ``FrameStats.discarded_bytes`` (or the
        warm-up's, :meth:`Session.warm_up`)."""
        self.totals.discarded_bytes += nbytes
        self.totals.discarded_levels += 1
        self.frame_discarded += nbytes

    def _requeue(self, b: Block) -> None:
        """Put ``b`` back in the queue if it still wants more (caller holds the lock)."""
        if not self.queue.retryable(b):
            return
        if self.queue.backing_off(b, time.monotonic()) or self.fetchable(b) is not None:
            self.push(b)
        elif not self.fetching.get(b) and b in self.raw and b not in self.decoding:
            self._drop_raw(b)  # levels fetched beyond a gap that will not be filled

    # -- what a waiting frame lacks (Session.update(..., wait=True)) -------------------------

    def take_counts(self) -> FrameCounts:
        """What the loaders counted since the last frame, reset (hold :attr:`cv`)."""
        out = FrameCounts(self.frame_realtime, self.frame_prefetched, self.frame_io_s,
                          self.frame_late, self.frame_discarded, self.unreported)  # fmt: skip
        self.frame_realtime = self.frame_prefetched = self.frame_late = 0
        self.frame_discarded = 0
        self.frame_io_s = 0.0
        self.unreported = []
        return out

    def missing(self, needed: dict[Block, int]) -> list[tuple[Block, int]]:
        """The ``(block, level)`` of ``needed`` not resident yet, or without errors read."""
        errors, cache = self.errors, self.cache
        return [(b, lv) for b, lv in needed.items() if cache.level(b) < lv or b not in errors]

    def mark_demand(self, needed: dict[Block, int], due: float) -> None:
        """Mark the levels ``needed`` lacks as demanded, due at ``due`` unless due earlier
        (until each arrives)."""
        with self.cv:
            for b, lv in needed.items():
                for level in range(self.cache.level(b) + 1, lv + 1):
                    self.demanded.add((b, level))
                    self.due.setdefault((b, level), due)

    def requeue_idle(self, missing: list[tuple[Block, int]]) -> int:
        """Queue again the blocks of ``missing`` that are neither queued nor being read or
        decoded (caller holds the lock); how many. A level refused for lack of room (the
        budget held by loads in flight) leaves the queue (``LoadQueue.pop``), and so does a
        block the planning thread's rebuild did not know this frame wanted; no new frame
        queues them again while a wait is on: without this the wait ran into its timeout."""
        q = self.queue
        n = 0
        for b, _ in missing:
            if q.queued_key(b) is None and not self.fetching.get(b) and b not in self.decoding:
                self.push(b)
                n += 1
        return n

    # -- inline loading (workers=0) and shutdown -------------------------------------------

    def load_inline(self, allowance: int | None, deadline: float | None = None) -> bool:
        """``workers=0``: one pass of jobs on the caller's thread, up to ``allowance`` bytes
        read (loaded, or discarded on arrival: the same I/O) and until ``deadline``
        (``time.monotonic``): each ``(block, level)`` at most once and one retry of a failed
        block (``LoadQueue.pop``'s probe) unless nothing else is queued. A read that fails
        adds no bytes, and one slower than its retry's backoff (a server that stopped
        answering, each read ending at its timeout) once kept this loop retrying the most
        urgent block for ever. The pass ends when a block fails its last retry (the
        frame reports it at once). True when work is left that could run now."""
        spent = 0
        tried: set[Job] = set()
        held: list[Block] = []  # blocks whose next job this pass ran already: queued after

        def take(b: Block) -> int | None:
            if (b, self.fetchable(b)) in tried:
                held.append(b)
                return None  # out of the queue until the pass ends
            return self._take(b)

        probed = False
        try:
            while allowance is None or spent < allowance:
                if deadline is not None and time.monotonic() >= deadline:
                    return True
                with self.cv:
                    job = None if self.fatal is not None else self.next_job(not probed, take)
                    probed = probed or job in self.probes
                if job is None:
                    return bool(held)
                tried.add(job)
                t = self.totals
                before, failed = t.loaded_bytes + t.discarded_bytes, len(self.unreported)
                self.run_job(job)
                spent += t.loaded_bytes + t.discarded_bytes - before
                if len(self.unreported) > failed:
                    return True  # a block failed every retry: the frame reports it now
            return True
        finally:
            if held:
                with self.cv:
                    for b in held:
                        self._requeue(b)

    def busy(self) -> bool:
        """Whether jobs are queued or running (caller holds the lock)."""
        return bool(len(self.queue) or self._in_flight or self.decoding)

    def threads(self) -> list[threading.Thread]:
        """The loader threads started so far (alive or not; none without workers)."""
        return [] if self._pool is None else self._pool.threads

    def close(self, timeout_s: float) -> list[str]:
        """Stop taking jobs, wait (bounded) for running ones; names of threads still alive."""
        with self.cv:
            self.closed = True
            self.queue.clear()
            self.cv.notify_all()
        if self._pool is None:
            return []
        self._pool.shutdown(wait=False, cancel_futures=True)
        threads = self._pool.threads
        deadline = time.monotonic() + timeout_s
        for t in threads:
            t.join(timeout=max(0.0, deadline - time.monotonic()))
        return [t.name for t in threads if t.is_alive()]


def _storage(store: TerrainStore, levels: list[np.ndarray]) -> list[np.ndarray]:
    """Decoded heights back to the store's value units (quantised stores keep integers)."""
    p = store.meta.precision
    if not p:
        return levels
    return [np.rint(v.astype(np.float64) / p).astype(np.int32) for v in levels]
