"""The load queue: blocks by urgency, with cancellation and per-block retry backoff.

Pure bookkeeping (no threads, no I/O; the session's lock guards it). A block is queued with a
key (smaller = more urgent); :meth:`LoadQueue.rebuild` replaces the whole queue when the plan
changes and counts the blocks that dropped out (cancelled loads). A failed read puts its block
in backoff: ``backoff_s * 2**(n-1)`` after the ``n``-th failure in a row, capped at
``max_backoff_s``. After ``retries`` failures in a row the block is *failed* (reported in the
frame and the summary); when ``heal`` is on it is still retried, at the capped backoff, for as
long as it is wanted, and a success clears it. With ``heal`` off a failed block is never
retried (the behaviour before healing; kept as the positive control of the fault tests).

Failed blocks wait apart, taking turns by oldest failure (visible blocks' before prefetched
ones', by the first two fields of the loader's key): while one of their retries runs, every other
worker takes blocks that have not failed, and they have the workers only when nothing else is
queued. A server that fails slowly (a timeout per read) once kept every worker retrying the
same few most urgent failed blocks at the capped pace: blocks never read stayed queued until
the wait's deadline (a warm-up's 30 s), though the frame needed them.

Blocks in backoff sleep apart too, on a heap by retry time (:meth:`LoadQueue.pop` moves
them there when it meets them, :meth:`LoadQueue.rebuild` puts them there, a due time or a
success of the block wakes them). They once stayed in the urgency heaps, and every pop took
each of them out and put it back: during an outage a pop cost 12 ms with 5,000 queued
blocks (73 ms with 20,000; ``bench/outage_queue.py``), under the lock the caller waits on, on
every frame and every finished read.

A block is queued at most once per key: :meth:`LoadQueue.push` skips a block already queued
with a key at least as urgent (the caller re-queues every visible block that lacks a level on
every frame; without this the heap grew by those duplicates between rebuilds, thousands of
tuples that the caller's garbage collections had to walk).
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from itertools import islice
from typing import TypeVar

from streamer.cache import Block

T = TypeVar("T")


class LoadQueue:
    """Blocks waiting for a load, most urgent first (see module doc)."""

    def __init__(
        self, *, retries: int, backoff_s: float, max_backoff_s: float, heal: bool = True
    ) -> None:
        self.retries = retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max(backoff_s, max_backoff_s)
        self.heal = heal
        #: while the caller waits (set by the wait, None otherwise): the start of its wait;
        #: blocks that gave up since then (:meth:`given_up`) are not retried until it ends
        self.waiting_since: float | None = None
        self._heap: list[tuple[tuple, Block]] = []
        #: ``((errors-first, pinned, last failure, key), block)``: see :meth:`_failed_entry`
        self._failed: list[tuple[tuple, Block]] = []
        #: blocks in backoff: ``(retry time, seq, block)`` by retry time, with the keys of each
        #: sleeping block in ``_asleep`` (an entry whose block is not there any more is stale)
        self._sleeping: list[tuple[float, int, Block]] = []
        self._asleep: dict[Block, list[tuple]] = {}
        self._n_asleep = 0
        self._seq = 0
        #: while a rebuild sorts: the blocks read successfully since it began (see
        #: :meth:`rebuild_steps`), else None
        self._recovered: set[Block] | None = None
        self._best: dict[Block, tuple] = {}  # most urgent key each queued block has
        self.failures: dict[Block, int] = {}  # failures in a row
        self.retry_at: dict[Block, float] = {}
        self.failed_at: dict[Block, list[float]] = {}  # times of the latest failures
        self.cancelled = 0

    def __len__(self) -> int:
        return len(self._heap) + len(self._failed) + self._n_asleep

    def blocks(self) -> set[Block]:
        """Every queued block."""
        return {b for _, b in self._heap} | {b for _, b in self._failed} | self._asleep.keys()

    def clear(self) -> None:
        """Drop every queued block."""
        self._heap.clear()
        self._failed.clear()
        self._drop_sleepers()
        self._best.clear()

    def _drop_sleepers(self) -> None:
        self._sleeping = []
        self._asleep = {}  # (new: a rebuild still reads the old one)
        self._n_asleep = 0

    def _sleep(self, key: tuple, b: Block) -> None:
        """Put ``(key, b)``, in backoff, on the sleeping heap until its retry time."""
        keys = self._asleep.get(b)
        if keys is None:
            keys = self._asleep[b] = []
            self._seq += 1
            heapq.heappush(self._sleeping, (self.retry_at[b], self._seq, b))
        keys.append(key)
        self._n_asleep += 1

    def _wake(self, now: float) -> None:
        """Queue again the sleeping blocks whose retry time has come (one whose retry time
        moved on sleeps again until then)."""
        sleeping = self._sleeping
        while sleeping and sleeping[0][0] <= now:
            _, _, b = heapq.heappop(sleeping)
            keys = self._asleep.get(b)
            if keys is None:
                continue  # stale: woken by a success, or dropped by a rebuild
            if self.backing_off(b, now):  # failed again meanwhile: a later retry time
                self._seq += 1
                heapq.heappush(sleeping, (self.retry_at[b], self._seq, b))
                continue
            self._wake_block(b)

    def _wake_block(self, b: Block) -> None:
        keys = self._asleep.pop(b)
        self._n_asleep -= len(keys)
        for key in keys:
            self._enqueue(key, b)

    def retryable(self, b: Block) -> bool:
        """False for a failed block when healing is off."""
        return self.heal or self.failures.get(b, 0) < self.retries

    def queued_key(self, b: Block) -> tuple | None:
        """The most urgent key ``b`` is queued with (None: not queued)."""
        return self._best.get(b)

    def push(self, b: Block, key: tuple) -> None:
        """Queue ``b`` with ``key`` (ignored for a block that may not be retried, and for one
        already queued with a key at least as urgent)."""
        best = self._best.get(b)
        if (best is None or key < best) and self.retryable(b):
            self._enqueue(key, b)
            self._best[b] = key

    def _failed_entry(self, key: tuple, b: Block) -> tuple[tuple, Block]:
        """A failed block's place: by its key's class (its first two fields: the loader's
        errors-first and pinned flags, so a visible block still goes before a prefetch one),
        then by oldest failure (the turns), then by key."""
        return (*key[:2], self.failed_at[b][-1], key), b

    def _enqueue(self, key: tuple, b: Block) -> None:
        """Put ``(key, b)`` on the heap of its class: failed blocks apart (module doc)."""
        if self.is_failed(b):
            heapq.heappush(self._failed, self._failed_entry(key, b))
        else:
            heapq.heappush(self._heap, (key, b))

    def rebuild(self, items: Iterable[tuple[tuple, Block]], now: float | None = None) -> None:
        """Replace the queue; blocks no longer in it count as cancelled. Given ``now``, the
        blocks then in backoff go straight to sleep (else the next pop puts them there)."""
        for _ in self.rebuild_steps(list(items), now):
            pass

    def rebuild_steps(
        self, items: list[tuple[tuple, Block]], now: float | None = None, chunk: int = 64
    ) -> Iterator[None]:
        """:meth:`rebuild` in steps: the new heaps are built apart, ``chunk`` items a step,
        then put in place in one short step (the owner holds the lock during each step and
        may release it between them). A block that fails, recovers or is taken between the
        steps sits where it was sorted until a pop meets it, which re-checks it (as for a
        block whose state changes after any rebuild). No step walks a large queue: the blocks
        in backoff (most of it in an outage) go on a new sleeping heap as they are sorted
        (the swap put each to sleep again, one by one), a large queue's heaps grow by pushes
        (a small one's are heapified in a step of their own), and a large old queue, no
        longer shared once swapped, is compared with the new one ``4 * chunk`` entries a step
        to count the cancelled loads."""
        heap: list[tuple[tuple, Block]] = []
        failed: list[tuple[tuple, Block]] = []
        asleep: dict[Block, list[tuple]] = {}  # the new sleepers, on their own heap
        sleeping: list[tuple[float, int, Block]] = []
        n_asleep = 0
        best: dict[Block, tuple] = {}
        step = 4 * chunk
        large = len(items) > step
        if large:
            put, put_failed = partial(heapq.heappush, heap), partial(heapq.heappush, failed)
        else:  # (heapified in a step of their own)
            put, put_failed = heap.append, failed.append
        kept: set[Block] = set()  # best's blocks as sorted, if large (pops change best)
        outer = self._recovered  # (a rebuild inside another's steps shares its set)
        self._recovered = recovered = set() if outer is None else outer
        try:
            for i in range(0, len(items), chunk):
                for k, b in items[i : i + chunk]:
                    if self.retryable(b):
                        if now is not None and self.backing_off(b, now):
                            keys = asleep.get(b)
                            if keys is None:
                                keys = asleep[b] = []
                                self._seq += 1
                                heapq.heappush(sleeping, (self.retry_at[b], self._seq, b))
                            keys.append(k)
                            n_asleep += 1
                        elif self.is_failed(b):
                            put_failed(self._failed_entry(k, b))
                        else:
                            put((k, b))
                        if b not in best:
                            best[b] = k
                            if large:
                                kept.add(b)
                        elif k < best[b]:
                            best[b] = k
                yield
            if not large:
                heapq.heapify(heap)
                heapq.heapify(failed)
                yield
        finally:  # (recoveries are recorded until the swap)
            self._recovered = outer
        old_heap, old_failed, old_asleep = self._heap, self._failed, self._asleep
        n_old = len(old_heap) + len(old_failed) + len(old_asleep)
        self._heap, self._failed = heap, failed
        self._sleeping, self._asleep, self._n_asleep = sleeping, asleep, n_asleep
        for b in recovered:  # (their sleeping entries are stale: see _wake)
            if b in asleep and b not in self.retry_at:
                self._wake_block(b)
        # the cancelled loads: the blocks of the old queue not in the new one
        gone: set[Block] = set()
        if n_old <= step:  # small: in this step, before a pop changes best
            gone.update(b for _, b in old_heap)
            gone.update(b for _, b in old_failed)
            gone.update(old_asleep)
            self._best = best
            self.cancelled += len(gone - best.keys())
            return
        self._best = best
        if not large:
            kept = set(best)
        parts = [(b for _, b in old_heap), (b for _, b in old_failed), iter(old_asleep)]
        for n, blocks in zip((len(old_heap), len(old_failed), len(old_asleep)), parts, strict=True):
            for _ in range(0, n, step):
                yield
                gone.update(b for b in islice(blocks, step) if b not in kept)
        self.cancelled += len(gone)

    def backing_off(self, b: Block, now: float) -> bool:
        """Whether ``b`` waits for its next retry."""
        return self.retry_at.get(b, 0.0) > now

    def pop(
        self, now: float, take: Callable[[Block], T | None], probe: bool = True
    ) -> tuple[Block, T] | None:
        """The most urgent block ``take`` accepts (``take`` returns its job or None), skipping
        blocks in backoff (they stay queued) and dropping those ``take`` refuses. With
        ``probe`` (no retry of a failed block runs) a failed block goes first, the one that
        failed longest ago in the most urgent class; without it failed blocks go only when no
        other block can (module doc). While a waiter waits (:attr:`waiting_since`), failed
        blocks that gave up since it began stay queued untried: retrying them only kept a
        worker from the blocks it still waited for (a warm-up over a failing server read each
        block up to 13 times instead of ``retries``), and healing resumes once it ends."""
        self._wake(now)
        waiting: list[tuple[tuple, Block]] = []
        found = None
        best, since = self._best, self.waiting_since
        heaps = (self._failed, self._heap) if probe else (self._heap, self._failed)
        for heap in heaps:
            failed_heap = heap is self._failed
            while heap:
                entry, b = heapq.heappop(heap)
                key = entry[-1] if failed_heap else entry
                if best.get(b) == key:
                    del best[b]
                if not self.retryable(b):
                    continue
                if self.backing_off(b, now):
                    self._sleep(key, b)
                    best[b] = key if b not in best else min(key, best[b])
                    continue
                if not failed_heap and self.is_failed(b):
                    waiting.append((key, b))  # failed since it was queued: to its heap
                    continue
                if failed_heap and since is not None and self.given_up(b, since):
                    waiting.append((key, b))  # the waiter no longer waits for it
                    continue
                job = take(b)
                if job is not None:
                    found = (b, job)
                    break
            if found is not None:
                break
        for key, b in waiting:
            self._enqueue(key, b)
            if b not in best or key < best[b]:
                best[b] = key
        return found

    def failed_read(self, b: Block, now: float) -> int:
        """Record a failed read of ``b``; returns its failures in a row."""
        n = self.failures.get(b, 0) + 1
        self.failures[b] = n
        times = self.failed_at.setdefault(b, [])
        times.append(now)
        del times[: -self.retries]  # the last ``retries`` are enough
        if self.retryable(b):
            delay = min(self.backoff_s * 2 ** (n - 1), self.max_backoff_s)
            self.retry_at[b] = now + delay
        return n

    def succeeded(self, b: Block) -> None:
        """A read of ``b`` worked: forget its failures (and wake it if it sleeps)."""
        self.failures.pop(b, None)
        self.retry_at.pop(b, None)
        self.failed_at.pop(b, None)
        if b in self._asleep:
            self._wake_block(b)
        if self._recovered is not None:
            self._recovered.add(b)

    def is_failed(self, b: Block) -> bool:
        """``b`` failed ``retries`` times in a row (and has not been read since)."""
        return self.failures.get(b, 0) >= self.retries

    def given_up(self, b: Block, since: float) -> bool:
        """Whether a waiter that started at ``since`` stops waiting for ``b``: it is failed
        and, when healing, ``retries`` more reads since then failed too (a fresh round of
        retries; without healing a failed block never returns)."""
        if not self.is_failed(b):
            return False
        if not self.heal:
            return True
        return sum(t >= since for t in self.failed_at.get(b, ())) >= self.retries

    def failed_blocks(self) -> set[Block]:
        """Every block currently failed."""
        return {b for b, n in self.failures.items() if n >= self.retries}

    def next_retry(self, now: float) -> float | None:
        """Seconds until the earliest pending retry (None if none)."""
        ahead = [t - now for t in self.retry_at.values() if t > now]
        return min(ahead) if ahead else None
