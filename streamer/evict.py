"""The eviction order of :class:`streamer.cache.LevelCache` and the questions a loader asks
of it (a mixin over the cache's entries; no threads, the session holds its lock).

To make room, levels above a block's want go first (least recently wanted blocks first), then
wanted but unpinned levels (lowest priority first); pinned levels are never evicted. Under
pressure (from the first eviction until a plan finds the cache half empty) the order is kept
in three heaps as entries change, and a refused room's walk is kept as the index that answers
the next refusals (:meth:`EvictionIndex._freeable`).
"""

from __future__ import annotations

import heapq
from bisect import bisect_left
from dataclasses import dataclass, field
from itertools import accumulate

import numpy as np

Block = tuple[int, int]


Block = tuple[int, int]


@dataclass
class Entry:
    """One block's record in the cache: its resident levels, want, pin and eviction key."""

    levels: list[np.ndarray] = field(default_factory=list)
    nbytes: int = 0
    want: int = -1  # level wanted by the current frame, prefetch included (-1: none)
    pin: int = -1  # level the current frame needs to draw the block (-1: not visible)
    priority: float = 0.0  # larger = more important among prefetched blocks
    last_wanted: int = 0  # frame number when last wanted (a pinned block: now, see _wanted_at)
    ikey: tuple | None = None  # its item in the eviction heaps (None: nothing may go)
    ver: int = 0  # the version its live heap item carries (LevelCache._index)


def bytes_above(e: Entry, keep: int) -> int:
    """Bytes of ``e``'s levels above ``keep``."""
    return sum(a.nbytes for a in e.levels[keep + 1 :])


class EvictionIndex:
    """The eviction half of :class:`streamer.cache.LevelCache` (its entries, pins, budget and
    heaps are the cache's own attributes)."""

    _entries: dict[Block, Entry]
    _pins: dict[Block, int]
    _heaps: tuple[list, list, list]
    _indexed: bool
    _ver: int
    _gen: int
    _free_gen: int
    _free: tuple[int, list[float], list[int]]
    budget: int
    nbytes: int
    reserved: int
    frame: int
    evicted_bytes: int
    # and its methods _wanted_at (the frame a block was last wanted) and drop_level

    def _victim_key(self, block: Block, e: Entry) -> tuple | None:
        """``block``'s eviction key (smaller goes first), None if nothing of it may go: levels
        above what anyone wants first, stalest first; then levels wanted ahead of time (not
        needed to draw this frame), least important first (:meth:`_heap_key`'s classes)."""
        k = self._heap_key(block, e)
        if k is None:
            return None
        if k[0] == 2:
            return (1, k[1], k[2])
        return (0, self._wanted_at(block, e), k[-2])

    def _victims(self) -> list[tuple[tuple, Block]]:
        """Evictable (block, finest level) candidates, best victim first."""
        key = self._victim_key
        out = [(k, b) for b, e in self._entries.items() if (k := key(b, e)) is not None]
        out.sort()  # ties by block id: the order does not hang on how entries were made
        return out

    def _index(self, block: Block, e: Entry) -> None:
        """Put ``block``'s eviction key on its heap after a change of its levels, want, pin,
        priority or last want, while the heaps are kept (its older item goes stale). Its key
        is the one :meth:`_victims` sorts by, split three ways so that no item has to change
        when only the frame does: a pinned block's levels above its want are "wanted now"
        (the current frame, compared when popped)."""
        if not self._indexed:
            return
        k = self._heap_key(block, e)
        if k == e.ikey:
            return
        e.ikey = k
        if k is None:
            return
        self._ver += 1
        e.ver = self._ver
        heap = self._heaps[k[0]]
        heapq.heappush(heap, (*k[1:], e.ver))
        if len(heap) > 4 * len(self._entries) + 64:  # mostly stale items: rebuild
            self._reheap(k[0])

    def _heap_key(self, block: Block, e: Entry) -> tuple | None:
        """``(heap, *item)`` of ``block``'s eviction key (None: nothing of it may go)."""
        if not e.levels:
            return None
        top = len(e.levels) - 1
        if top > e.want:
            return (1, -top, block) if block in self._pins else (0, e.last_wanted, -top, block)
        if top > e.pin:
            return (2, e.priority, -top, block)
        return None

    def _reheap(self, which: int) -> None:
        """Heap ``which`` from the live items only."""
        heap = [
            (*e.ikey[1:], e.ver)
            for e in self._entries.values()
            if e.ikey is not None and e.ikey[0] == which
        ]
        heapq.heapify(heap)
        self._heaps[which][:] = heap

    def _build_index(self) -> None:
        """Start keeping the eviction heaps: every entry's key, heaped at once."""
        self._indexed = True
        for b, e in self._entries.items():
            e.ikey = self._heap_key(b, e)
            self._ver += 1
            e.ver = self._ver
        for which in (0, 1, 2):
            self._reheap(which)

    def _drop_index(self) -> None:
        """Stop keeping the eviction heaps (their items all go stale)."""
        self._indexed = False
        for heap in self._heaps:
            heap.clear()

    def _live_top(self, which: int, skip: Block | None, aside: list) -> tuple | None:
        """The smallest live item of heap ``which`` (stale ones dropped; ``skip``'s item set
        ``aside``), as the key :meth:`_victims` sorts by, followed by the block."""
        heap, entries = self._heaps[which], self._entries
        while heap:
            item = heap[0]
            b = item[-2]
            e = entries.get(b)
            if e is None or e.ver != item[-1] or e.ikey is None or e.ikey[0] != which:
                heapq.heappop(heap)
            elif b == skip:
                aside.append((which, heapq.heappop(heap)))
            elif which == 0:
                return (0, item[0], item[1], b)
            elif which == 1:
                return (0, self.frame, item[0], b)
            else:
                return (1, item[0], item[1], b)
        return None

    def make_room(self, nbytes: int, for_block: Block | None = None) -> bool:
        """Evict (finest levels first) until ``nbytes`` more fit; False if pins prevent it.

        Victims in :meth:`_victims`' order, from the heaps :meth:`_index` keeps: a take that
        must evict once walked and sorted every entry under the lock."""
        if self.nbytes + nbytes <= self.budget:
            return True
        if not self._indexed:
            self._build_index()  # the first eviction since the cache was half empty
        aside: list = []
        try:
            while self.nbytes + nbytes > self.budget:
                tops = [t for w in (0, 1, 2) if (t := self._live_top(w, for_block, aside))]
                if not tops:
                    return False
                self.drop_level(min(tops)[-1])
            return True
        finally:
            for which, item in aside:
                heapq.heappush(self._heaps[which], item)

    def may_add(self, block: Block, level: int, nbytes: int) -> bool:
        """Whether loading ``level`` of ``block`` now is worth it and can fit."""
        e = self._entries.get(block)
        if e is None or level > e.want or level != len(e.levels):
            return False
        return self.nbytes + nbytes <= self.budget or self._room_possible(block, nbytes)

    def room_for(self, block: Block, nbytes: int) -> bool:
        """Whether ``nbytes`` more for ``block`` fit, evicting only what may go for it: a
        prefetch load never evicts a more important prefetched level (that would thrash)."""
        return self.nbytes + nbytes <= self.budget or self._room_possible(block, nbytes)

    def _room_possible(self, block: Block, nbytes: int) -> bool:
        """Whether evicting what may go for ``block`` frees enough: every level above its
        block's want, and the levels wanted ahead (above their pins) of blocks less important
        than ``block`` when its level is itself ahead of time, of any block otherwise; never
        ``block``'s own.

        A walk that stops once enough is found; one that finds too little has seen every
        entry and keeps what it saw (:meth:`_freeable`'s index), which answers the next
        questions in O(log n) until an entry changes: a loader's refused take, repeated down
        the queue, once walked and sorted every entry under the lock each time (and a
        refusal walked the entries twice: the search, then the index)."""
        e_new = self._entries[block]
        ahead = e_new.pin < len(e_new.levels)  # the level to load is above the block's pin
        short = self.nbytes + nbytes - self.budget  # bytes to free
        if self._free_gen != self._gen:
            free, p_new, stale, held = 0, e_new.priority, 0, []
            for b, e in self._entries.items():
                lv = e.levels
                if not lv:
                    continue
                top = len(lv) - 1
                if top > e.want:  # (the index's classes: _heap_key's)
                    n = bytes_above(e, e.want)
                    stale += n
                elif top > e.pin:
                    held.append(e)  # (only the entry: most walks stop early)
                    if ahead and e.priority >= p_new:
                        continue
                    n = bytes_above(e, e.pin)
                else:
                    continue
                if b != block:
                    free += n
                    if free >= short:
                        return True
            self._keep_free(stale, [(e.priority, bytes_above(e, e.pin)) for e in held])
            return free >= short  # (what the index answers below: short may be <= 0)
        stale, prio, cum = self._freeable()
        free = stale + (cum[bisect_left(prio, e_new.priority)] if ahead else cum[-1])
        own = self._victim_key(block, e_new)
        if own is not None and own[0] == 0:
            free -= bytes_above(e_new, e_new.want)
        elif own is not None and not ahead:  # (ahead: its own priority is not below itself)
            free -= bytes_above(e_new, e_new.pin)
        return free >= short

    def _freeable(self) -> tuple[int, list[float], list[int]]:
        """``(bytes above their blocks' wants, the priorities of the blocks holding levels
        wanted ahead (sorted), the running sums of those levels' bytes in that order)``, kept
        until an entry's levels, want, pin or priority change."""
        if self._free_gen != self._gen:
            stale, held = 0, []
            for b, e in self._entries.items():
                k = self._heap_key(b, e)
                if k is None:
                    continue
                if k[0] == 2:
                    held.append((e.priority, bytes_above(e, e.pin)))
                else:
                    stale += bytes_above(e, e.want)
            self._keep_free(stale, held)
        return self._free

    def _keep_free(self, stale: int, held: list[tuple[float, int]]) -> None:
        """Keep :meth:`_freeable`'s index of the current entries: ``stale`` bytes above their
        wants, ``held`` ``(priority, bytes)`` of the levels wanted ahead."""
        held.sort()
        prio = [p for p, _ in held]
        self._free = (stale, prio, list(accumulate((n for _, n in held), initial=0)))
        self._free_gen = self._gen

    def reserve(self, block: Block, nbytes: int) -> bool:
        """Count ``nbytes`` of a level being fetched for ``block`` (evicting if needed)."""
        if not self.make_room(nbytes, for_block=block):
            return False
        self.nbytes += nbytes
        self.reserved += nbytes
        self.peak_held = max(self.peak_held, self.nbytes)
        return True

    def release(self, nbytes: int) -> None:
        """Give back a reservation that will not become a level."""
        self.nbytes -= nbytes
        self.reserved -= nbytes
