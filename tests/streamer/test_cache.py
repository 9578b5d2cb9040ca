"""The byte-budgeted level cache: a Hypothesis state machine never sees the budget exceeded."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from streamer.cache import LevelCache
from streamer.errors import BudgetError

LEVEL_BYTES = [8 * (4**i) for i in range(5)]  # 8, 32, 128, 512, 2048 bytes
BLOCKS = [(r, c) for r in range(3) for c in range(3)]


def level_array(level: int) -> np.ndarray:
    return np.zeros(LEVEL_BYTES[level] // 8, dtype=np.float64)


class CacheMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.cache = LevelCache(budget_bytes=4000)

    @rule(
        wants=st.dictionaries(
            st.sampled_from(BLOCKS),
            st.tuples(st.integers(-1, 4), st.booleans(), st.floats(0, 10)),
            max_size=6,
        )
    )
    def set_wants(self, wants):
        wants = {b: (lv, lv if vis else -1, prio) for b, (lv, vis, prio) in wants.items()}
        visible_need = sum(sum(LEVEL_BYTES[: pin + 1]) for _, pin, _ in wants.values())
        if visible_need > self.cache.budget:
            with pytest.raises(BudgetError, match="raise budget_mb or the error threshold tau"):
                self.cache.set_wants(wants, LEVEL_BYTES)
        else:
            self.cache.set_wants(wants, LEVEL_BYTES)

    @rule(block=st.sampled_from(BLOCKS))
    def load_next(self, block):
        level = self.cache.level(block) + 1
        want, _pin = self.cache.want(block)
        if level > 4 or level > want:
            assert not self.cache.may_add(block, level, LEVEL_BYTES[min(level, 4)])
            return
        pinned_before = self.cache.pinned_bytes()
        added = self.cache.add_level(block, level, level_array(level))
        if added:
            assert self.cache.level(block) == level
        # visible data needed by the frame is never evicted to make room
        assert self.cache.pinned_bytes() >= pinned_before

    @precondition(lambda self: self.cache.blocks())
    @rule(data=st.data())
    def drop(self, data):
        block = data.draw(st.sampled_from(self.cache.blocks()))
        lv = self.cache.level(block)
        self.cache.drop_level(block)
        assert self.cache.level(block) == lv - 1

    @rule(linger=st.integers(0, 3))
    def trim(self, linger):
        self.cache.trim(linger)

    @invariant()
    def never_over_budget(self):
        assert 0 <= self.cache.nbytes <= self.cache.budget
        assert self.cache.peak_nbytes <= self.cache.peak_held <= self.cache.budget
        total = sum(sum(a.nbytes for a in self.cache.levels(b)) for b in self.cache.blocks())
        assert total + self.cache.reserved == self.cache.nbytes


TestCacheMachine = CacheMachine.TestCase
TestCacheMachine.settings = settings(max_examples=60, stateful_step_count=40, deadline=None)


def test_visible_set_larger_than_budget_is_a_clear_error():
    cache = LevelCache(100)
    with pytest.raises(BudgetError, match=r"need .* \(2,728 bytes\) .* budget is .* \(100 bytes\)"):
        cache.set_wants({(0, 0): (4, 4, 1.0)}, LEVEL_BYTES)


def test_prefetch_is_evicted_before_visible():
    cache = LevelCache(8 + 32 + 128 + 512 + 8 + 32)
    cache.set_wants({(0, 0): (2, 2, 1.0), (0, 1): (2, -1, 0.5)}, LEVEL_BYTES)
    for lv in range(3):
        assert cache.add_level((0, 1), lv, level_array(lv))
    for lv in range(3):
        assert cache.add_level((0, 0), lv, level_array(lv))
    cache.set_wants({(0, 0): (3, 3, 1.0), (0, 1): (2, -1, 0.5)}, LEVEL_BYTES)
    assert cache.add_level((0, 0), 3, level_array(3))
    assert cache.level((0, 0)) == 3
    assert cache.level((0, 1)) == 1  # the prefetched block gave up its finest level
    assert cache.nbytes == cache.budget


def test_rejects_bad_budget():
    with pytest.raises(BudgetError, match="got 0"):
        LevelCache(0)


def test_reservations_count_against_the_budget_not_as_resident():
    """A level being read holds budget (``peak_held``) but is not resident until it arrives:
    ``peak_nbytes`` once counted reservations, so a session whose reads all failed reported a
    peak resident above the bytes it ever loaded. The control: the level arriving makes both
    peaks its size."""
    c = LevelCache(1000)
    c.set_wants({(0, 0): (0, 0, 1.0)}, [400])
    assert c.reserve((0, 0), 400)
    assert (c.peak_nbytes, c.peak_held) == (0, 400)
    c.release(400)  # the read failed
    assert (c.nbytes, c.peak_nbytes, c.peak_held) == (0, 0, 400)
    assert c.reserve((0, 0), 400)
    assert c.add_level((0, 0), 0, np.zeros(100, np.float32), reserved=True)
    assert (c.nbytes, c.peak_nbytes, c.peak_held) == (400, 400, 400)
