"""Where each block's quadtree texture lives in ``geometry-splitting``'s one GPU buffer (pure
bookkeeping, no GL). A block's slot is as large as its texture (a few sizes: how deep the
texture is stored node by node, ``pure.texture_nodes``); a freed slot goes to the next texture
of its size. A released key's slot keeps its texture, idle, until a new texture needs the room
(the oldest idle first), so a block that comes back finds it. The buffer grows only when the
live textures need it, or to keep idle ones while under a cache size. Before, a dropped
block's slot was never reused and every growth doubled the buffer, so along a flight it grew
with the blocks ever seen, not with those on the GPU (BENCHMARKS.md "The texture buffer")."""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Sequence


class SlotTable:
    """Slots in a buffer of :attr:`capacity` elements. :attr:`offset` maps each live key to its
    slot's first element (the dict is updated in place, never replaced), :attr:`size_of` each
    key with a slot (live or idle) to its size."""

    def __init__(
        self, headroom: float = 2.0, limit: int | None = None, cache: int = 0, minimum: int = 0
    ) -> None:
        if headroom < 1.0 or cache < 0 or minimum < 0:
            raise ValueError(
                f"headroom {headroom} must be >= 1, cache {cache} and minimum {minimum} >= 0"
            )
        self.headroom = headroom
        self.limit = limit  # most elements there can be (every block's largest texture)
        self.cache = cache  # elements the buffer may grow to only to keep idle textures
        self.minimum = minimum  # elements of the first buffer, at least (each growth copies)
        self.capacity = 0
        self.offset: dict[Hashable, int] = {}
        self.size_of: dict[Hashable, int] = {}
        self._idle: dict[Hashable, int] = {}  # released keys' slots, oldest first
        self._free: dict[int, list[int]] = {}  # size -> offsets of slots nobody holds
        self._end = 0  # elements handed out since the last compaction

    def __len__(self) -> int:
        return len(self.offset)

    @property
    def idle(self) -> list[Hashable]:
        """The released keys whose slots still hold their contents, oldest first."""
        return list(self._idle)

    def live_elements(self) -> int:
        """Elements of the live keys' slots."""
        return sum(self.size_of[key] for key in self.offset)

    def release(self, key: Hashable) -> None:
        """Make ``key``'s slot idle (no-op for a key that is not live)."""
        off = self.offset.pop(key, None)
        if off is not None:
            self._idle[key] = off

    def release_all_but(self, live: Iterable[Hashable]) -> list[Hashable]:
        """Release every live key not in ``live``; the keys released."""
        keep = set(live)
        gone = [key for key in self.offset if key not in keep]
        for key in gone:
            self.release(key)
        return gone

    def revive(self, key: Hashable) -> bool:
        """Make released ``key`` live again in its old slot, if no other key has taken it."""
        off = self._idle.pop(key, None)
        if off is None:
            return False
        self.offset[key] = off
        return True

    def _drop(self, key: Hashable) -> None:
        """Free ``key``'s slot (live or idle) for any key of its size."""
        off = self.offset.pop(key, None)
        if off is None:
            off = self._idle.pop(key, None)
        size = self.size_of.pop(key, None)
        if off is not None and size is not None:
            self._free.setdefault(size, []).append(off)

    def _fits(self, wants: Sequence[tuple[Hashable, int]]) -> tuple[bool, int]:
        """Whether :meth:`reserve` of every ``(key, size)`` in turn needs no growth, and how
        many idle slots it would take."""
        free = {s: len(v) for s, v in self._free.items()}
        idle: dict[int, int] = {}
        for key in self._idle:
            idle[self.size_of[key]] = idle.get(self.size_of[key], 0) + 1
        end, taken = self._end, 0
        for key, size in wants:
            if key in self.offset and self.size_of[key] == size:
                continue
            if key in self.size_of:  # its old slot is freed first
                old = self.size_of[key]
                free[old] = free.get(old, 0) + 1
            if free.get(size, 0):
                free[size] -= 1
            elif end + size <= self.capacity:
                end += size
            elif idle.get(size, 0):
                idle[size] -= 1
                taken += 1
            else:
                return False, taken
        return True, taken

    def grow_to(self, wants: Sequence[tuple[Hashable, int]]) -> int | None:
        """The capacity (elements) to grow to before ``wants`` are reserved, or ``None`` when
        they fit. For live textures: :attr:`headroom` times the live and wanted ones. Where
        idle slots would do, the buffer still grows (by :attr:`headroom`) to keep them while
        it is under :attr:`cache`; past that the oldest idle slot of the size gives way. At
        least :attr:`minimum`, never past :attr:`limit`, never below the live and wanted
        textures."""
        idle = [key for key, _ in wants if key in self._idle]
        if idle:  # (placing one could evict another of the same batch)
            raise ValueError(f"revive the idle keys {idle} before reserving them")
        ok, taken = self._fits(wants)
        if ok and not taken:
            return None
        # (a key changing size keeps its old slot until the compaction is over: counted)
        need = self.live_elements() + sum(size for _, size in wants)
        if ok:  # only to keep the idle textures cached
            held = need + sum(self.size_of[k] for k in self._idle)
            want = min(max(int(self.headroom * self.capacity + 0.5), held), self.cache)
            if self.limit is not None:
                want = min(want, self.limit)
            return want if want > self.capacity else None
        want = max(int(self.headroom * need + 0.5), self.minimum)
        if self.limit is not None:
            want = min(want, self.limit)
        return max(want, need, self.capacity)  # (the capacity itself: compacted, sizes mixed)

    def compact(
        self, capacity: int, keep_free: int = 0
    ) -> tuple[list[tuple[Hashable, int, int]], list[Hashable]]:
        """Give the buffer ``capacity`` elements: the live slots back to back from 0 (in
        their order), then the most recently released idle ones that fit with ``keep_free``
        elements left. ``(key, old offset, new offset)`` for each kept slot (to copy its
        contents), and the idle keys dropped."""
        live = self.live_elements()
        if capacity < live:
            raise ValueError(f"{capacity} elements cannot hold the live slots' {live}")
        kept, room = [], capacity - live - keep_free
        for key in reversed(self._idle):  # newest first
            if self.size_of[key] <= room:
                kept.append(key)
                room -= self.size_of[key]
        kept.reverse()
        keep = set(kept)
        dropped = [key for key in self._idle if key not in keep]
        moves, end = [], 0
        for key, off in [*self.offset.items(), *((k, self._idle[k]) for k in kept)]:
            moves.append((key, off, end))
            end += self.size_of[key]
        for key, _, new in moves[: len(self.offset)]:
            self.offset[key] = new
        self._idle = {key: new for key, _, new in moves[len(self.offset) :]}
        for key in dropped:
            del self.size_of[key]
        self._free.clear()
        self._end, self.capacity = end, capacity
        return moves, dropped

    def reserve(self, key: Hashable, size: int) -> tuple[int, Hashable | None]:
        """A slot of ``size`` elements for ``key`` (its own if live or idle with that size;
        else its old one is freed): a free slot of the size first, then unused space, then the
        oldest idle slot of the size (that key is forgotten). Its offset and the key evicted
        (``None``). Grow first when :meth:`grow_to` says so (for a batch without idle keys:
        :meth:`revive` them first, else one could evict another)."""
        if size < 1:
            raise ValueError(f"a slot of {size} elements")
        if self.size_of.get(key) == size and (key in self.offset or self.revive(key)):
            return self.offset[key], None
        self._drop(key)
        evicted = None
        if self._free.get(size):
            off = self._free[size].pop()
        elif self._end + size <= self.capacity:
            off, self._end = self._end, self._end + size
        else:
            evicted = next((k for k in self._idle if self.size_of[k] == size), None)
            if evicted is None:
                raise RuntimeError(f"no slot of {size} elements for {key!r}: grow first")
            off = self._idle.pop(evicted)
            del self.size_of[evicted]
        self.offset[key], self.size_of[key] = off, size
        return off, evicted
