"""``LevelCache.set_pins`` touches only the pins that changed: the same cache as the eager
version (every pin rewritten each frame, kept here as the reference) over random sequences."""

from __future__ import annotations

import random

import numpy as np
import pytest

from streamer.cache import LevelCache
from streamer.evict import Entry

LEVEL_BYTES = [8 * (4**i) for i in range(5)]
BLOCKS = [(r, c) for r in range(4) for c in range(4)]


def sorting_make_room(self, nbytes, for_block=None):
    """The eviction before its heaps (926f81a): every drop walks and sorts all entries."""
    while self.nbytes + nbytes > self.budget:
        victims = [v for v in self._victims() if v[1] != for_block]
        if not victims:
            return False
        self.drop_level(victims[0][1])
    return True


def sorting_room_possible(self, block, nbytes):
    """``_room_possible`` before its index (926f81a): a walk and a sort per question."""
    freeable = 0
    e_new = self._entries[block]
    for key, b in self._victims():
        if b == block:
            continue
        if key[0] == 1 and key[1] >= e_new.priority and e_new.pin < len(e_new.levels):
            continue
        e = self._entries[b]
        keep = e.want if key[0] == 0 else e.pin
        freeable += sum(a.nbytes for a in e.levels[keep + 1 :])
    return self.nbytes + nbytes - freeable <= self.budget


def eager_prefetch_steps(self, wants, chunk=64):
    """``prefetch_steps`` before the eviction heaps (926f81a): every entry outside ``wants``
    rewritten, wanted or not already."""
    entries = self._entries
    keys = list(entries)
    for i in range(0, len(keys), chunk):
        self._gen += 1
        for b in keys[i : i + chunk]:
            e = entries.get(b)
            if e is not None and b not in wants:
                e.want, e.priority = e.pin, 0.0
                if not e.levels and e.want < 0:
                    del entries[b]
        yield
    items = list(wants.items())
    for i in range(0, len(items), chunk):
        self._gen += 1
        for b, (lv, prio) in items[i : i + chunk]:
            e = entries.get(b)
            if e is None:
                e = entries[b] = Entry()
            e.want, e.priority = max(lv, e.pin), prio
            if lv >= 0:
                e.last_wanted = self.frame
            elif not e.levels and e.want < 0:
                del entries[b]
        yield


def one_hold_trim(self, linger_frames=0):
    """``trim`` before its steps (07bf328): every entry walked in one call."""
    before = self.nbytes
    for b in list(self._entries):
        e = self._entries.get(b)
        while (
            e is not None
            and len(e.levels) - 1 > max(e.want, -1)
            and self.frame - self._wanted_at(b, e) > linger_frames
        ):
            self.drop_level(b)
            e = self._entries.get(b)
    return before - self.nbytes


class EagerCache(LevelCache):
    """The cache as it was: every pin and ``last_wanted`` rewritten on every call, every
    unwanted entry's want on every plan, and the eviction that sorts every entry (it does not
    keep the eviction heaps)."""

    make_room = sorting_make_room
    _room_possible = sorting_room_possible
    prefetch_steps = eager_prefetch_steps

    def level(self, block):
        e = self._entries.get(block)
        return len(e.levels) - 1 if e else -1

    def set_pins(self, pins, level_bytes, need=None):
        cum = self._cumulative(level_bytes)
        need = sum(cum[pin] for pin in pins.values() if pin >= 0)
        if need > self.budget:
            raise AssertionError("the sequences stay under the budget")
        self.frame += 1
        entries = self._entries
        for b in self._pins:
            if b not in pins:
                e = entries.get(b)
                if e is not None:
                    e.pin = -1
                    if not e.levels and e.want < 0:
                        del entries[b]
        for b, pin in pins.items():
            e = entries.get(b)
            if e is None:
                e = entries[b] = Entry()
            e.pin = pin
            if pin > e.want:
                e.want = pin
            e.last_wanted = self.frame
        self._pins = dict(pins)

    def _wanted_at(self, block, e):
        return e.last_wanted


def observe(c: LevelCache) -> tuple:
    return (
        [c.level(b) for b in BLOCKS],
        c.levels_of(BLOCKS),
        [c.want(b) for b in BLOCKS],
        sorted(c.wanted()),
        c._victims(),
        c.nbytes,
        c.pinned_bytes(),
        sorted(c.blocks()),
    )


def step(rng: random.Random, caches: list[LevelCache], negative: bool, last: list) -> list:
    op = rng.choice(["pins", "pins", "prefetch", "add", "add", "add", "drop", "trim"])
    lo = -1 if negative else 0
    if op == "pins":
        if last and rng.random() < 0.5:  # consecutive frames often pin the same levels
            pins = last[0]
        else:
            pins = {b: rng.randint(lo, 2) for b in rng.sample(BLOCKS, rng.randint(0, 6))}
            last[:] = [pins]
        return [c.set_pins(dict(pins), LEVEL_BYTES) for c in caches]
    if op == "prefetch":
        wants = {b: (rng.randint(-1, 4), rng.random()) for b in rng.sample(BLOCKS, 5)}
        return [c.set_prefetch(dict(wants)) for c in caches]
    b = rng.choice(BLOCKS)
    if op == "add":
        lv = caches[0].level(b) + 1
        if lv > 4:
            return []
        return [c.add_level(b, lv, np.zeros(LEVEL_BYTES[lv] // 8)) for c in caches]
    if op == "drop":
        if caches[0].level(b) < 0:
            return []
        return [c.drop_level(b) for c in caches]
    linger = rng.randint(0, 3)
    return [c.trim(linger) for c in caches]


@pytest.mark.parametrize("negative", [False, True])
@pytest.mark.parametrize("seed", range(40))
def test_set_pins_by_difference_keeps_the_eager_caches_behaviour(seed, negative):
    rng = random.Random(seed)
    caches = [LevelCache(3000), EagerCache(3000)]
    last: list = []
    for _ in range(300):
        out = step(rng, caches, negative, last)
        assert out == out[:1] * len(out)
        assert observe(caches[0]) == observe(caches[1])


def test_the_comparison_sees_a_stale_last_wanted():
    """The control: a cache that never refreshes a pinned block's ``last_wanted`` (what the
    difference would do without :meth:`LevelCache._wanted_at`) differs from the reference."""

    class Stale(LevelCache):
        def _wanted_at(self, block, e):
            return e.last_wanted

    differ = 0
    for seed in range(40):
        rng = random.Random(seed)
        caches = [Stale(3000), EagerCache(3000)]
        last: list = []
        for _ in range(300):
            step(rng, caches, False, last)
            if observe(caches[0]) != observe(caches[1]):
                differ += 1
                break
    assert differ >= 10
