"""A byte-budgeted cache of decoded block levels (no threads; the session holds its lock).

A block is resident as its levels ``0..L`` (decoded heights in sequence order); levels arrive
one at a time, coarse first, and leave finest first. Each block may carry a *want* (the level to
load, ahead of time included) and a *pin* (the level the current frame needs to draw it; -1 for
blocks that are only prefetched). Resident bytes never exceed the budget: to make room, levels
above a block's want go first (least recently wanted blocks first), then wanted but unpinned
levels (lowest priority first); pinned levels are never evicted.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from decimal import ROUND_CEILING, Decimal, localcontext
from itertools import chain, islice, repeat

import numpy as np

from streamer.errors import BudgetError
from streamer.evict import Block, Entry, EvictionIndex
from tiler.errors import LayoutError
from tiler.grid import as_block

__all__ = ["Block", "LevelCache", "PinChanges", "mib_text"]


@dataclass(frozen=True)
class PinChanges:
    """What :meth:`LevelCache.set_pins` would change, found by :meth:`LevelCache.pin_changes`
    before the owner's lock is taken."""

    of: dict[Block, int]  # the pins it was found for
    prev: dict[Block, int]  # the pins it was found against
    gone: set[Block]  # pinned before, not now
    moved: list[tuple[Block, int]]  # pinned now at another level than before, or new
    pins: dict[Block, int]  # the new pins (a copy)
    prev_negative: bool  # a previous pin is below 0 (the session never pins below 0)


def mib_text(n: int) -> str:
    """``n`` bytes as ``"X MiB (n bytes)"``, X rounded *up* to 4 significant digits: a budget
    of X MiB holds ``n`` bytes, and one byte count always reads the same."""
    with localcontext() as ctx:
        ctx.prec = 60  # n / 2**20 exactly (a terminating decimal)
        v = Decimal(int(n)) / Decimal(2**20)
        if v > 0:
            v = v.quantize(Decimal(1).scaleb(v.adjusted() - 3), rounding=ROUND_CEILING)
        return f"{format(v.normalize(), 'f')} MiB ({int(n):,} bytes)"


_mib = mib_text


class LevelCache(EvictionIndex):
    """Decoded levels of blocks under a byte budget; visible wants are pinned (the eviction
    order and the room questions: :class:`streamer.evict.EvictionIndex`)."""

    def __init__(self, budget_bytes: int, shape: tuple[int, int] | None = None) -> None:
        if budget_bytes <= 0:
            raise BudgetError(f"budget must be a positive number of bytes, got {budget_bytes}")
        self.budget = int(budget_bytes)
        # the block grid's (rows, cols): a block id outside it is refused (None: not checked)
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))
        self._entries: dict[Block, Entry] = {}
        self.nbytes = 0  # resident levels + reservations of levels being read
        self.peak_nbytes = 0  # largest resident (decoded levels only)
        self.peak_held = 0  # largest resident + reserved: what the budget bounds
        self.frame = 0
        self.evicted_bytes = 0
        self.reserved = 0  # bytes of levels being fetched (counted in nbytes)
        self._pins: dict[Block, int] = {}  # the current frame's pins (set_pins' argument)
        self._top: dict[Block, int] = {}  # finest resident level of blocks holding any
        self._moved: set[Block] = set()  # blocks whose finest level changed since the
        # previous take_level_changes
        self._cum: list[int] = []
        self._cum_key: list[int] | None = None
        # what evictions could free, rebuilt when an entry's levels, want, pin or priority
        # changed (``_gen`` counts those changes): see _freeable
        self._gen = 0
        self._free_gen = -1
        self._free: tuple[int, list[float], list[int]] = (0, [], [0])
        # the eviction heaps (see _index): levels above the want of unpinned blocks, of pinned
        # blocks, and levels wanted ahead above the pin; items whose version is not their
        # entry's any more are stale and skipped. Kept only while the budget is under pressure
        # (``_indexed``: from the first eviction until a plan finds the cache half empty)
        self._heaps: tuple[list, list, list] = ([], [], [])
        self._ver = 0
        self._indexed = False
        # blocks that want a level they do not hold (want > finest resident): what the load
        # queue is rebuilt from (short_steps), kept at every change of a want or a level
        self._short: set[Block] = set()
        # the latest plan's wants (prefetch_steps keeps its dict) and the blocks whose pin
        # changed since: the only entries the next plan may have to reset; every other entry
        # has want == pin and priority 0
        self._last_wants: dict[Block, tuple[int, float]] = {}
        self._repinned: set[Block] = set()

    def check_block(self, block: object) -> None:
        """Raise ``LayoutError`` (a ValueError) naming ``block`` and the grid unless it is a
        block id ``(row, col)`` inside the cache's grid (no check without a ``shape``): such an
        id once read as a block holding nothing (``levels((-1, -1))`` gave ``[]``)."""
        shape = self.shape
        if shape is None:
            return
        if type(block) is tuple and len(block) == 2:
            r, c = block
            if type(r) is int and type(c) is int and 0 <= r < shape[0] and 0 <= c < shape[1]:
                return
        r, c = as_block(block)  # (a LayoutError for what is no block id at all)
        if not (0 <= r < shape[0] and 0 <= c < shape[1]):
            raise LayoutError(
                f"block {block!r} is outside the {shape[0]}x{shape[1]}-block grid (rows "
                f"0..{shape[0] - 1}, columns 0..{shape[1] - 1})"
            )

    def level(self, block: Block) -> int:
        """Finest resident level of a block (-1 if none)."""
        top = self._top.get(block)
        if top is None:
            self.check_block(block)  # (only on a miss: the per-frame lookups stay one get)
            return -1
        return top

    def levels_of(self, blocks: Iterable[Block]) -> list[int]:
        """:meth:`level` of each block (one C-level pass: for the per-frame loops)."""
        return list(map(self._top.get, blocks, repeat(-1)))

    def levels_array(self, blocks: Sequence[Block]) -> np.ndarray:
        """:meth:`levels_of` as an int64 array."""
        return np.fromiter(map(self._top.get, blocks, repeat(-1)), np.int64, count=len(blocks))

    def take_level_changes(self) -> dict[Block, int]:
        """The finest resident level (-1: none) of each block whose level changed since the
        previous call (the owner holds its lock): a copy of :meth:`level` kept up to date from
        these answers stays equal to it, and can be read without the lock."""
        moved, self._moved = self._moved, set()
        get = self._top.get
        return {b: get(b, -1) for b in moved}

    def levels(self, block: Block) -> list[np.ndarray]:
        """The block's resident levels (a new list; arrays are shared, read-only)."""
        e = self._entries.get(block)
        if e is None:
            self.check_block(block)
            return []
        return list(e.levels)

    def blocks(self) -> list[Block]:
        """Blocks with at least one resident level."""
        return [b for b, e in self._entries.items() if e.levels]

    def pinned_bytes(self) -> int:
        """Bytes of resident levels that the current frame pins."""
        return sum(sum(a.nbytes for a in e.levels[: e.pin + 1]) for e in self._entries.values())

    def set_wants(
        self,
        wants: dict[Block, tuple[int, int, float]],
        level_bytes: list[int],
    ) -> None:
        """Replace every block's want: ``block -> (want level, pinned level, priority)``.

        Raises ``BudgetError`` if the pinned levels alone need more than the budget.
        """
        self.set_pins({b: pin for b, (_, pin, _) in wants.items() if pin >= 0}, level_bytes)
        self.set_prefetch({b: (lv, prio) for b, (lv, _, prio) in wants.items()})

    def pin_changes(self, pins: dict[Block, int]) -> PinChanges:
        """The blocks whose pin :meth:`set_pins` would change. Reads only the current pins,
        which only :meth:`set_pins` replaces: the thread that sets the pins may call this
        without the owner's lock, and hand the answer to :meth:`set_pins` under it."""
        prev = self._pins
        prev_pin = prev.get
        moved = [(b, pin) for b, pin in pins.items() if prev_pin(b, -2) != pin]
        negative = bool(prev) and min(prev.values()) < 0
        return PinChanges(pins, prev, prev.keys() - pins.keys(), moved, dict(pins), negative)

    def set_pins(
        self,
        pins: dict[Block, int],
        level_bytes: list[int],
        need: int | None = None,
        changes: PinChanges | None = None,
    ) -> None:
        """Replace the pinned levels (what this frame draws); other wants stay. ``need``: the
        bytes of the pinned levels, if the caller has summed them; ``changes``: what
        :meth:`pin_changes` found for ``pins`` (found again if the pins changed since; do not
        change ``pins`` in between).

        Raises ``BudgetError`` (changing nothing) if the pins alone exceed the budget. Touches
        only the blocks whose pin changed since the previous call (a pinned block counts as
        wanted now without a write, see :meth:`_wanted_at`): it runs on the caller's thread.
        """
        if need is None:
            cum = self._cumulative(level_bytes)
            need = sum(cum[pin] for pin in pins.values() if pin >= 0)
        if need > self.budget:
            raise BudgetError(
                "the visible blocks need {need} at their levels but the budget is {budget}; "
                "raise {budget_mb} or the error threshold {tau}",
                params={"budget_mb": "budget_mb", "tau": "tau"},
                need=_mib(need),
                budget=_mib(self.budget),
            )
        if changes is None or changes.of is not pins or changes.prev is not self._pins:
            changes = self.pin_changes(pins)
        if self.shape is not None:  # new entries are the only way a wrong id gets in
            entries = self._entries
            for b, _ in changes.moved:
                if b not in entries:
                    self.check_block(b)  # (before anything changes)
        self.frame += 1
        entries, prev = self._entries, self._pins
        gen = self._gen
        changed = []
        for b in changes.gone:
            e = entries.get(b)
            if e is not None:
                self._gen = gen + 1
                changed.append(b)
                e.pin = -1
                # pinned up to the previous frame (a prefetch may have said later since)
                e.last_wanted = max(e.last_wanted, self.frame - 1)
                if not e.levels and e.want < 0:
                    del entries[b]
                    self._short.discard(b)
        # a block pinned at the same level as before keeps its entry as it is: its want is
        # still >= its pin (every writer of a want keeps that) and a pinned entry with a
        # level >= 0 is never deleted; a pin < 0 is rewritten like a new one
        for b, pin in changes.moved:
            self._gen = gen + 1
            changed.append(b)
            e = entries.get(b)
            if e is None:
                e = entries[b] = Entry()
            e.pin = pin
            if pin > e.want:
                e.want = pin
                self._mark_short(b, e)
            e.last_wanted = self.frame
        if changes.prev_negative:
            for b, pin in prev.items():
                if pin < 0 and pins.get(b) == pin and b not in entries:
                    entries[b] = Entry(pin=pin, last_wanted=self.frame)
                    changed.append(b)
        self._repinned.update(changed)
        self._pins = changes.pins
        if self._indexed:  # (after the new pins: whether a block is pinned orders it)
            for b in changed:
                e = entries.get(b)
                if e is not None:
                    self._index(b, e)

    def _mark_short(self, block: Block, e: Entry) -> None:
        """Keep ``block`` in the short set while it wants a level it does not hold."""
        if e.want >= len(e.levels):
            self._short.add(block)
        else:
            self._short.discard(block)

    def _wanted_at(self, block: Block, e: Entry) -> int:
        """The frame in which ``block`` was last wanted: the current one while it is pinned."""
        return self.frame if block in self._pins else e.last_wanted

    def _cumulative(self, level_bytes: list[int]) -> list[int]:
        """``cum[L]`` = bytes of levels ``0..L`` (cached per ``level_bytes`` list)."""
        if self._cum_key is not level_bytes:
            self._cum = [sum(level_bytes[: i + 1]) for i in range(len(level_bytes))]
            self._cum_key = level_bytes
        return self._cum

    def set_prefetch(self, wants: dict[Block, tuple[int, float]]) -> None:
        """Replace the levels to load ahead: ``block -> (level, priority)``; pins stay."""
        for _ in self.prefetch_steps(wants):
            pass

    def prefetch_steps(
        self, wants: dict[Block, tuple[int, float]], chunk: int = 64
    ) -> Iterator[None]:
        """:meth:`set_prefetch` in steps of at most ``chunk`` blocks: the owner holds its lock
        during each step and may release it between steps (a reader between steps sees some
        wants old and some new, never a broken entry). The cache keeps ``wants`` until the next
        plan (what that plan may have to reset): do not change it."""
        entries, short = self._entries, self._short
        if self._indexed and self.nbytes <= self.budget // 2:
            self._drop_index()  # no pressure now: the heaps are not worth their upkeep
        # only the blocks the previous plan wanted, or whose pin changed since, can hold a
        # want or priority to reset (every other entry has want == pin, priority 0): scanned
        # a few per step (2 chunks at most, at most a chunk of them rewritten) instead of
        # walking every entry
        last, self._last_wants = self._last_wants, wants
        repinned, self._repinned = self._repinned, set()  # (later pin changes join the new)
        rest = chain(last, repinned)
        try:
            more = True
            while more:
                self._gen += 1
                touched = 0
                more = False
                for scanned, b in enumerate(rest, 1):
                    e = None if b in wants else entries.get(b)
                    if e is not None:
                        touched += 1
                        reset = e.want != e.pin or e.priority
                        if reset:
                            e.want, e.priority = e.pin, 0.0
                        if not e.levels and e.want < 0:
                            del entries[b]
                            short.discard(b)
                        elif reset:
                            self._mark_short(b, e)
                            if self._indexed:
                                self._index(b, e)
                    if touched >= chunk or scanned >= 2 * chunk:
                        more = True
                        break
                yield
        finally:  # (a plan stopped between its steps: the next one resets the rest)
            self._repinned.update(rest)
        # the wants a chunk per step, straight from the dict: a list of its items made every
        # item a new tuple in the first step's hold (~90 us at p50 on the 64x64-block store,
        # up to 0.5 ms when a collection of those tuples fell in it)
        pending = iter(wants.items())
        while True:
            self._gen += 1
            n = 0
            for b, (lv, prio) in islice(pending, chunk):
                n += 1
                e = entries.get(b)
                if e is None:
                    self.check_block(b)
                    e = entries[b] = Entry()
                w = lv if lv > e.pin else e.pin
                e.priority = prio
                if w != e.want:  # (_mark_short, inline, and only on a change: ~600 a plan)
                    e.want = w
                    if w >= len(e.levels):
                        short.add(b)
                    else:
                        short.discard(b)
                if lv >= 0:
                    e.last_wanted = self.frame
                elif not e.levels and w < 0:
                    del entries[b]
                    short.discard(b)
                    continue
                if self._indexed:
                    self._index(b, e)
            yield
            if n < chunk:
                return

    def short_steps(self, chunk: int = 64) -> Iterator[list[tuple[Block, int, int, float]]]:
        """``(block, want, pin, priority)`` of the blocks that want a level they do not hold,
        in steps of at most ``chunk`` blocks (see :meth:`prefetch_steps`); kept as wants and
        levels change, so a rebuild of the load queue need not walk every entry."""
        keys = list(self._short)
        for i in range(0, len(keys), chunk):
            out = []
            for b in keys[i : i + chunk]:
                e = self._entries.get(b)
                if e is not None and e.want >= len(e.levels):
                    out.append((b, e.want, e.pin, e.priority))
            yield out

    def wanted(self) -> list[tuple[Block, int, int, float]]:
        """``(block, want, pin, priority)`` of every block that wants something."""
        return [(b, e.want, e.pin, e.priority) for b, e in self._entries.items() if e.want >= 0]

    def want(self, block: Block) -> tuple[int, int]:
        """``(wanted level, pinned level)`` of a block (``(-1, -1)`` if unwanted)."""
        e = self._entries.get(block)
        if e is None:
            self.check_block(block)
            return (-1, -1)
        return (e.want, e.pin)

    def want_priority(self, block: Block) -> tuple[int, int, float]:
        """``(wanted level, pinned level, priority)`` of a block (``(-1, -1, 0.0)`` if
        unwanted)."""
        e = self._entries.get(block)
        if e is None:
            self.check_block(block)
            return (-1, -1, 0.0)
        return (e.want, e.pin, e.priority)

    def add_level(
        self, block: Block, level: int, values: np.ndarray, *, reserved: bool = False
    ) -> bool:
        """Add the next level of a block, evicting others if needed; False if it cannot fit.

        With ``reserved=True`` the bytes were reserved by :meth:`reserve` (always fits).
        """
        e = self._entries.get(block)
        if e is None:
            if reserved:
                self.release(int(values.nbytes))
            self.check_block(block)
            return False
        if level != len(e.levels):
            raise ValueError(f"block {block}: level {level} arrived but {len(e.levels)} is next")
        n = int(values.nbytes)
        if reserved:
            self.release(n)
        elif not self.make_room(n, for_block=block):
            return False
        values = np.asarray(values)
        values.setflags(write=False)
        self._gen += 1
        e.levels.append(values)
        self._top[block] = level
        self._moved.add(block)
        e.nbytes += n
        self.nbytes += n
        self._mark_short(block, e)
        self._index(block, e)
        self.peak_nbytes = max(self.peak_nbytes, self.nbytes - self.reserved)
        self.peak_held = max(self.peak_held, self.nbytes)
        return True

    def drop_level(self, block: Block) -> None:
        """Unload a block's finest level."""
        e = self._entries.get(block)
        if e is None or not e.levels:
            self.check_block(block)
            raise ValueError(f"block {block!r} holds no level to unload")
        self._gen += 1
        a = e.levels.pop()
        self._moved.add(block)
        if e.levels:
            self._top[block] = len(e.levels) - 1
        else:
            del self._top[block]
        e.nbytes -= a.nbytes
        self.nbytes -= a.nbytes
        self.evicted_bytes += a.nbytes
        if not e.levels and e.want < 0:
            del self._entries[block]
            self._short.discard(block)
        else:
            self._mark_short(block, e)
            self._index(block, e)

    def trim(self, linger_frames: int = 0) -> int:
        """Unload levels above their block's want once unwanted for more than ``linger_frames``.

        Returns the bytes unloaded.
        """
        return sum(self.trim_steps(linger_frames, len(self._entries) or 1))

    def trim_steps(self, linger_frames: int = 0, chunk: int = 64) -> Iterator[int]:
        """:meth:`trim` in steps of at most ``chunk`` blocks, each yielding the bytes it
        unloaded (see :meth:`prefetch_steps`: the owner may release its lock between steps;
        in one hold, a plan's trim walked every entry and dropped every stale level)."""
        entries = self._entries
        keys = list(entries)
        for i in range(0, len(keys), chunk):
            before = self.nbytes
            for b in keys[i : i + chunk]:
                e = entries.get(b)
                while (
                    e is not None
                    and len(e.levels) - 1 > max(e.want, -1)
                    and self.frame - self._wanted_at(b, e) > linger_frames
                ):
                    self.drop_level(b)
                    e = entries.get(b)
            yield before - self.nbytes
