"""Eviction under a budget smaller than the flight: ``LevelCache.room_for`` answers from an
index kept between changes, and ``make_room`` takes its victims from heaps kept as entries
change. Both must decide and evict exactly as the versions that walked and sorted every entry
on each call (kept in ``test_cache_pins.py`` as the reference), over random sequences of pins,
prefetch wants, loads, reservations, drops and trims (in steps, against the one-call trim)."""

from __future__ import annotations

import random

import numpy as np
import pytest
from test_cache_pins import (
    BLOCKS,
    LEVEL_BYTES,
    eager_prefetch_steps,
    observe,
    one_hold_trim,
    sorting_make_room,
    sorting_room_possible,
)

from streamer.cache import LevelCache
from streamer.errors import BudgetError


class SortingCache(LevelCache):
    """The eviction as it was: every call walks and sorts all entries (``evictions``: the
    calls that evicted something)."""

    evictions = 0
    _room_possible = sorting_room_possible
    prefetch_steps = eager_prefetch_steps
    trim = one_hold_trim

    def make_room(self, nbytes, for_block=None):
        before = self.evicted_bytes
        ok = sorting_make_room(self, nbytes, for_block)
        self.evictions += self.evicted_bytes > before
        return ok


_END = object()


def _raises(fn, *args) -> str | None:
    try:
        fn(*args)
    except BudgetError as exc:
        return type(exc).__name__
    return None


OPS = ["pins", "prefetch", "prefetch", "take", "take", "take", "room", "room", "add", "add", "add",
       "arrive", "drop", "trim", "shed"]  # fmt: skip


def step(rng: random.Random, caches: list[LevelCache], reserved: list[int]) -> list:
    op = rng.choice(OPS)
    if op == "pins":  # pins over the budget raise, changing nothing: both must
        pins = {b: rng.randint(0, 2) for b in rng.sample(BLOCKS, rng.randint(0, 4))}
        return [_raises(c.set_pins, dict(pins), LEVEL_BYTES) for c in caches]
    if op == "prefetch":  # priorities from a few values: ties between blocks happen
        wants = {b: (rng.randint(-1, 4), rng.choice([0.1, 0.5, 0.5, 2.0, rng.random()]))
                 for b in rng.sample(BLOCKS, rng.randint(3, 10))}  # fmt: skip
        # in steps of 2 blocks, as the session applies a plan. Between the steps the index
        # must answer as a walk of the same state (the steps themselves differ: the reference
        # rewrites every entry, the cache only those a plan may have to reset); the states
        # after the last step are compared by the caller
        steps = [c.prefetch_steps(dict(wants), 2) for c in caches]
        while [next(g, _END) for g in steps] != [_END] * len(steps):
            assert rooms(caches[0]) == walked_rooms(caches[0])
        return []
    wanted = [x for x in BLOCKS if caches[0].want(x)[0] >= 0]
    if op in ("take", "room", "add", "arrive"):  # the loader loads only wanted blocks
        if not wanted:
            return []
        b = rng.choice(wanted)
    else:
        b = rng.choice(BLOCKS)
    lv = caches[0].level(b) + 1
    n = LEVEL_BYTES[min(lv, 4)]
    if op == "take":  # the loader's _take: room for the next level, then reserve it
        out = [c.room_for(b, n) and c.reserve(b, n) for c in caches]
        if out[0]:
            reserved.append(n)
        return out
    if op == "room":
        return [c.room_for(b, n) for c in caches]
    if op == "arrive" and reserved:  # a reserved read ends (as a level when it is next)
        r = reserved.pop(rng.randrange(len(reserved)))
        return [c.release(r) for c in caches]
    if op in ("add", "arrive"):
        if lv > 4:
            return []
        return [c.add_level(b, lv, np.zeros(LEVEL_BYTES[lv] // 8)) for c in caches]
    if op == "drop":
        return [] if lv == 0 else [c.drop_level(b) for c in caches]
    if op == "shed":  # every level of a few blocks goes: the cache empties now and then, and
        for x in rng.sample(BLOCKS, 6):  # the eviction heaps are dropped and built again
            for _ in range(caches[0].level(x) + 1):
                for c in caches:
                    c.drop_level(x)
        return []
    linger = rng.randint(0, 3)  # in steps of 2 blocks, as the session's planning thread trims
    return [sum(caches[0].trim_steps(linger, 2)), *(c.trim(linger) for c in caches[1:])]


def rooms(c: LevelCache) -> list[bool]:
    """What evicting could make room for, asked of every wanted block at every level size
    (whether or not the budget is full: the answer a stale index would get wrong)."""
    return [c._room_possible(b, n) for b in BLOCKS if c.want(b)[0] >= 0 for n in LEVEL_BYTES]


def walked_rooms(c: LevelCache) -> list[bool]:
    """:func:`rooms` answered by the reference's walk over ``c``'s entries."""
    return [
        sorting_room_possible(c, b, n) for b in BLOCKS if c.want(b)[0] >= 0 for n in LEVEL_BYTES
    ]


def short_blocks(c: LevelCache) -> list:
    """The blocks :meth:`LevelCache.short_steps` gives (what the load queue is built from)."""
    return sorted(b for part in c.short_steps(3) for b, *_ in part)


def walked_short(c: LevelCache) -> list:
    """The blocks that want a level they do not hold, found by walking every entry."""
    return sorted(b for b, e in c._entries.items() if e.want >= len(e.levels))


def _compare(seed: int, budget: int, cls: type[LevelCache] = LevelCache) -> tuple[int, int]:
    """Run a sequence on both caches, asserting equal answers and states at every step (and
    that ``cls``'s short set is what a walk finds); return how many steps refused a load and
    how many evicted."""
    rng = random.Random(seed)
    caches = [cls(budget), SortingCache(budget)]
    reserved: list[int] = []
    refused = 0
    for _ in range(500):
        out = step(rng, caches, reserved)
        assert out == out[:1] * len(out)
        assert observe(caches[0]) == observe(caches[1])
        assert caches[0].evicted_bytes == caches[1].evicted_bytes
        assert rooms(caches[0]) == rooms(caches[1])
        assert short_blocks(caches[0]) == walked_short(caches[0])
        refused += out[:1] == [False]
    return refused, caches[1].evictions


class _NoShortSet(LevelCache):
    """A short set that a level's departure (a drop, an eviction, a trim) does not update."""

    def drop_level(self, block):
        short = set(self._short)
        super().drop_level(block)
        self._short = short


class _PinBlind(LevelCache):
    """A plan that does not reset the blocks whose pin changed since the previous plan."""

    def set_pins(self, pins, level_bytes, need=None):
        repinned = set(self._repinned)
        super().set_pins(pins, level_bytes, need)
        self._repinned = repinned


@pytest.mark.parametrize("cls", [_NoShortSet, _PinBlind])
def test_the_comparison_sees_a_stale_short_set_or_an_unreset_want(cls):
    """The controls of the short set and of the plan's resets (which no longer walk every
    entry): a short set not updated when a level leaves, or a plan that does not reset a
    block unpinned since the previous plan, fails the comparison in most sequences."""
    failed = 0
    for seed in range(10):
        try:
            _compare(seed, 1500, cls)
        except AssertionError:
            failed += 1
    assert failed >= 5, failed


@pytest.mark.parametrize("budget", [600, 1500, 4000])
@pytest.mark.parametrize("seed", range(20))
def test_eviction_decides_as_the_sorting_reference(seed, budget):
    _compare(seed, budget)


def test_the_sequences_evict_refuse_and_keep_then_drop_the_heaps(monkeypatch):
    """The scene the comparison needs: budgets smaller than what the sequences ask for, so
    that loads are refused and ``make_room`` evicts many times, and caches that empty now and
    then, so that the heaps are dropped and built again."""
    calls = {"build": 0, "drop": 0}
    for name in calls:
        real = getattr(LevelCache, f"_{name}_index")

        def counted(self, _real=real, _name=name):
            calls[_name] += 1
            _real(self)

        monkeypatch.setattr(LevelCache, f"_{name}_index", counted)
    got = [_compare(seed, 600) for seed in range(20)]
    refused, evicted = sum(r for r, _ in got), sum(e for _, e in got)
    assert refused > 1000 and evicted > 300, (refused, evicted)
    assert calls["build"] >= 10 and calls["drop"] >= 3, calls


def test_the_comparison_sees_a_room_answer_off_by_one_priority():
    """The control: counting the wanted-ahead levels of blocks *as* important as the loading
    one (``<=`` where the reference has ``<``) is caught by the comparison."""
    from bisect import bisect_right

    import streamer.evict as evict_mod

    class Loose(LevelCache):
        def _room_possible(self, block, nbytes):
            e_new = self._entries[block]
            stale, prio, cum = self._freeable()
            ahead = e_new.pin < len(e_new.levels)
            free = stale + (cum[bisect_right(prio, e_new.priority)] if ahead else cum[-1])
            own = self._victim_key(block, e_new)
            if own is not None and own[0] == 0:
                free -= evict_mod.bytes_above(e_new, e_new.want)
            elif own is not None:
                free -= evict_mod.bytes_above(e_new, e_new.pin)
            return self.nbytes + nbytes - free <= self.budget

    differ = 0
    for seed in range(20):
        rng = random.Random(seed)
        caches = [Loose(600), SortingCache(600)]
        for _ in range(500):
            try:  # (a prefetch op compares the answers between its steps)
                out = step(rng, caches, [])
            except AssertionError:
                differ += 1
                break
            if out != out[:1] * len(out) or rooms(caches[0]) != rooms(caches[1]):
                differ += 1
                break
    assert differ >= 5, differ


def test_a_block_loading_for_itself_stays_a_victim_for_the_next():
    """``make_room(for_block=A)`` skips A's own levels; they stay first in line for the next
    block's room (A's heap item is set aside during the call, then put back)."""
    c = LevelCache(1000)
    for b in [(0, 0), (0, 1), (0, 2)]:
        c.set_prefetch({b: (2, 1.0)})
        for lv in range(3):
            c.add_level(b, lv, np.zeros(LEVEL_BYTES[lv] // 8))
    c.set_prefetch({(0, 1): (2, 1.0), (0, 2): (2, 1.0), (0, 0): (-1, 0.0)})
    # (0, 0) is above its want (-1): the stalest victim, but it loads for itself now
    assert c._victims()[0][1] == (0, 0)
    assert c.make_room(1000 - c.nbytes + 8, for_block=(0, 0))
    assert c.level((0, 0)) == 2  # its own levels stayed
    assert c.make_room(1000 - c.nbytes + 8, for_block=(0, 1))
    assert c.level((0, 0)) == 1  # ... and went first for another block


def test_the_heaps_stay_bounded():
    """Stale heap items are dropped: over many changes the heaps stay within a few times the
    entries (a heap that only grew would be a leak, and slow every pop)."""
    rng = random.Random(5)
    c = LevelCache(3000)
    for _ in range(5000):
        step(rng, [c], [])
        assert sum(map(len, c._heaps)) <= 3 * (4 * len(c._entries) + 65)


def _skipping_trim_steps(self, linger_frames=0, chunk=64):
    """A faulty ``trim_steps``: each step leaves its last block unvisited."""
    entries = self._entries
    keys = list(entries)
    for i in range(0, len(keys), chunk):
        before = self.nbytes
        for b in keys[i : i + chunk - 1]:
            e = entries.get(b)
            while (
                e is not None
                and len(e.levels) - 1 > max(e.want, -1)
                and self.frame - self._wanted_at(b, e) > linger_frames
            ):
                self.drop_level(b)
                e = entries.get(b)
        yield before - self.nbytes


def test_trims_in_steps_unload_and_a_step_skipping_a_block_is_caught(monkeypatch):
    """The sequences' trims in steps unload levels (a trim that never did would compare equal),
    and the control: a step that skips its last block is caught by the comparison."""
    trimmed: list[int] = []
    real = LevelCache.trim_steps

    def counting(self, linger_frames=0, chunk=64):
        for n in real(self, linger_frames, chunk):
            trimmed.append(n)
            yield n

    monkeypatch.setattr(LevelCache, "trim_steps", counting)
    for seed in range(20):
        _compare(seed, 1500)
    assert sum(n > 0 for n in trimmed) >= 20, trimmed
    monkeypatch.setattr(LevelCache, "trim_steps", _skipping_trim_steps)
    caught = 0
    for seed in range(20):
        try:
            _compare(seed, 1500)
        except AssertionError:
            caught += 1
    assert caught >= 5, caught


class _CountingDict(dict):
    """A dict whose ``items()`` walks are counted."""

    walks = 0

    def items(self):
        type(self).walks += 1
        return super().items()


def test_a_refusal_walks_the_entries_once_and_keeps_the_index():
    """A refused ``room_for`` walks the entries once, keeping what it saw: the refusals down
    the queue after it, and ``_freeable``, walk none until an entry changes (it walked them
    twice: the search, then the index). The control: after a change, the next refusal walks
    again, once, so the count sees the walks."""
    c = LevelCache(1000)
    blocks = [(0, j) for j in range(6)]
    c.set_pins({b: 0 for b in blocks}, LEVEL_BYTES)
    c.set_prefetch({b: (2, 1.0) for b in blocks})
    for b in blocks:
        c.add_level(b, 0, np.zeros(LEVEL_BYTES[0] // 8))
    c._entries = _CountingDict(c._entries)
    _CountingDict.walks = 0
    big = c.budget  # more than anything could free: every level held is pinned
    assert not c.room_for(blocks[0], big)
    assert _CountingDict.walks == 1
    assert not any(c.room_for(b, big) for b in blocks)
    c._freeable()
    assert _CountingDict.walks == 1
    c.add_level(blocks[0], 1, np.zeros(LEVEL_BYTES[1] // 8))  # a change: the index is stale
    assert not c.room_for(blocks[1], big)
    assert _CountingDict.walks == 2


def _pin_runs(forge: bool) -> int:
    """Random pins set with ``pin_changes`` found beforehand (as the session does, without the
    lock), and once with changes found before the pins moved on; returns how many runs ended
    in a state other than setting the pins plainly (``forge``: the stale changes dressed up as
    current, which the guard would refuse)."""
    from dataclasses import replace

    rng = random.Random(7)
    differ = 0
    for _ in range(60):
        a, ref = LevelCache(4000), LevelCache(4000)
        draw = [{b: rng.randint(0, 2) for b in rng.sample(BLOCKS, rng.randint(0, 6))}
                for _ in range(4)]  # fmt: skip
        for pins in draw[:2]:
            a.set_pins(pins, LEVEL_BYTES, changes=a.pin_changes(pins))
            ref.set_pins(pins, LEVEL_BYTES)
            assert observe(a) == observe(ref)
        q, r = draw[2], draw[3]
        stale = a.pin_changes(q)  # then the pins move on before it is used
        a.set_pins(r, LEVEL_BYTES)
        ref.set_pins(r, LEVEL_BYTES)
        if forge:
            stale = replace(stale, prev=a._pins)
        a.set_pins(q, LEVEL_BYTES, changes=stale)
        ref.set_pins(q, LEVEL_BYTES)
        differ += observe(a) != observe(ref)
    return differ


def test_pin_changes_found_beforehand_set_what_set_pins_does():
    """``LevelCache.pin_changes`` (the session finds them before taking the lock) gives the
    same state as ``set_pins`` finding them itself, and changes found before the pins moved on
    are found again, not used."""
    assert _pin_runs(forge=False) == 0


def test_positive_control_stale_pin_changes_used_as_found_differ():
    assert _pin_runs(forge=True) > 10
