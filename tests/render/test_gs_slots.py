"""``render.strategies.geometry_splitting.slots.SlotTable``: where each block's quadtree texture
sits in geometry-splitting's buffer (pure bookkeeping, no GL)."""

from __future__ import annotations

import numpy as np
import pytest

from render.strategies.geometry_splitting.slots import SlotTable


def _put(t: SlotTable, wants) -> list:
    """Reserve ``(key, size)`` pairs as the strategy does (grow first when told); the keys
    whose slots gave way."""
    wants = [(k, 1) if not isinstance(k, tuple) else k for k in wants]
    cap = t.grow_to(wants)
    dropped = t.compact(cap, sum(n for _, n in wants))[1] if cap is not None else []
    return dropped + [e for k, n in wants if (e := t.reserve(k, n)[1]) is not None]


def test_a_released_slot_goes_to_a_new_key_of_its_size():
    t = SlotTable(headroom=2.0)
    _put(t, [("a", 10), ("b", 10)])
    assert t.capacity == 40
    _put(t, [("c", 10), ("d", 10)])
    t.release("b")
    assert t.idle == ["b"] and t.grow_to([("e", 10)]) is None
    assert t.reserve("e", 10) == (10, "b")  # b's slot, b forgotten
    assert t.capacity == 40 and t.idle == [] and not t.revive("b") and "b" not in t.size_of
    assert sorted(t.offset.values()) == [0, 10, 20, 30]


def test_an_idle_slot_of_another_size_does_not_serve():
    t = SlotTable(headroom=1.0)
    _put(t, [("a", 10), ("b", 4)])
    t.release("a")
    # no 4-slot free nor idle: compacted at the same capacity (no cache: a gives way)
    assert t.grow_to([("c", 4)]) == 14
    assert _put(t, [("c", 4)]) == ["a"] and t.idle == [] and t.offset == {"b": 0, "c": 4}


def test_a_key_back_before_its_slot_is_taken_finds_it():
    t = SlotTable()
    _put(t, ["a", "b"])  # capacity 4
    t.release("a")
    _put(t, ["c", "d"])  # unused space first: a's slot is still a's
    assert t.revive("a") and t.offset["a"] == 0 and t.idle == []
    assert not t.revive("a")  # already live


def test_the_oldest_idle_slot_of_the_size_goes_first():
    t = SlotTable(headroom=1.0)
    _put(t, list("abcd"))
    for k in "cab":
        t.release(k)
    assert t.idle == ["c", "a", "b"]
    assert t.reserve("x", 1) == (2, "c") and t.reserve("y", 1) == (0, "a")
    assert t.idle == ["b"]


def test_reserving_an_idle_key_at_its_size_takes_its_own_slot():
    t = SlotTable()
    _put(t, [("a", 2), ("b", 2)])
    t.release("b")
    assert t.reserve("b", 2) == (2, None) and t.idle == []


def test_a_key_changing_size_frees_its_old_slot():
    t = SlotTable(headroom=1.0)
    _put(t, [("a", 3), ("b", 5)])
    assert t.grow_to([("a", 5)]) == 13  # live 8 + 5: compacted, then a placed anew
    _put(t, [("a", 5)])
    assert t.size_of == {"a": 5, "b": 5} and t.offset["a"] == 8
    assert _put(t, [("c", 3)]) == [] and t.offset["c"] == 0  # a's old 3-slot, no growth
    assert t.live_elements() == t.capacity == 13


def test_growth_is_headroom_times_the_live_and_wanted_elements():
    t = SlotTable(headroom=1.5)
    assert t.grow_to([("a", 4)]) == 6
    t.compact(6)
    t.reserve("a", 4)
    assert t.grow_to([("b", 2)]) is None and t.grow_to([("b", 3)]) == 11  # 10.5 rounded up
    assert SlotTable(headroom=1.0).grow_to([("a", 5)]) == 5


def test_the_first_buffer_is_at_least_the_minimum_within_the_limit():
    assert SlotTable(minimum=100).grow_to([("a", 3)]) == 100
    assert SlotTable(minimum=100, limit=40).grow_to([("a", 3)]) == 40
    assert SlotTable(minimum=10).grow_to([("a", 30)]) == 60  # headroom beyond it


def test_headroom_stops_at_the_limit_but_never_below_the_need():
    t = SlotTable(headroom=2.0, limit=10)
    assert t.grow_to([("a", 4)]) == 8 and t.grow_to([("a", 6)]) == 10
    assert t.grow_to([("a", 12)]) == 12  # more than the limit said: still room for them
    assert SlotTable(limit=None).grow_to([("a", 6)]) == 12


def test_compact_keeps_live_slots_then_the_newest_idle_ones_that_fit():
    t = SlotTable(headroom=2.0)
    _put(t, [("a", 5), ("b", 5), ("c", 5), ("d", 5)])  # capacity 40
    for k in "acb":
        t.release(k)
    moves, dropped = t.compact(15)
    assert moves == [("d", 15, 0), ("c", 10, 5), ("b", 5, 10)]
    assert dropped == ["a"] and "a" not in t.size_of
    assert t.offset == {"d": 0} and t.idle == ["c", "b"]
    assert t.revive("b") and t.offset["b"] == 10
    moves, dropped = t.compact(15, keep_free=5)  # room kept for a new slot: c gives way
    assert dropped == ["c"] and [m[0] for m in moves] == ["d", "b"]


def test_release_all_but_releases_only_the_others():
    t = SlotTable()
    _put(t, list("abc"))
    assert t.release_all_but(["b", "z"]) == ["a", "c"]
    assert list(t.offset) == ["b"] and t.idle == ["a", "c"]


def test_errors_name_the_problem():
    t = SlotTable()
    with pytest.raises(RuntimeError, match="grow first"):
        t.reserve("a", 3)
    with pytest.raises(ValueError, match="a slot of 0 elements"):
        t.reserve("a", 0)
    _put(t, ["a", "b"])
    with pytest.raises(ValueError, match="cannot hold the live slots' 2"):
        t.compact(1)
    with pytest.raises(ValueError, match="headroom 0.5"):
        SlotTable(headroom=0.5)
    with pytest.raises(ValueError, match="cache -1"):
        SlotTable(cache=-1)
    with pytest.raises(ValueError, match="minimum -2"):
        SlotTable(minimum=-2)
    t.release("nope")  # unknown: no-op
    assert len(t) == 2 and t.reserve("a", 1) == (t.offset["a"], None)  # already there


def test_idle_keys_are_kept_by_growing_while_under_the_cache():
    t = SlotTable(headroom=2.0, cache=6)
    _put(t, list("ab"))  # capacity 4
    t.release("a")
    t.release("b")
    assert _put(t, list("cd")) == []  # unused space
    assert t.grow_to([("e", 1)]) == 6  # idle a, b would do, but the cache allows keeping them
    assert _put(t, ["e"]) == [] and t.capacity == 6 and t.idle == ["a", "b"]
    assert _put(t, ["f"]) == [] and t.grow_to([("g", 1)]) is None  # full, at the cache: evict
    assert _put(t, ["g"]) == ["a"] and t.capacity == 6


def test_the_cache_never_grows_past_the_limit():
    t = SlotTable(headroom=2.0, limit=3, cache=100)
    _put(t, list("ab"))  # capacity 3 (the limit)
    t.release("a")
    assert _put(t, ["c"]) == [] and t.grow_to([("d", 1)]) is None
    assert _put(t, ["d"]) == ["a"] and t.capacity == 3


@pytest.mark.parametrize("seed", range(30))
def test_random_churn_keeps_slots_apart_and_the_buffer_bounded(seed):
    """Blocks come, go, come back and change texture size as along a flight: no two slots
    (live or idle) overlap, all lie inside the buffer, a revived key has the slot it had, and
    the buffer never exceeds ``headroom`` times the most elements live at once plus a
    wanted batch (+1 rounding), or the cache."""
    rng = np.random.default_rng(seed)
    h = float(rng.choice([1.0, 1.5, 2.0]))
    t = SlotTable(headroom=h, cache=int(rng.integers(0, 60)))
    sizes = (1, 3, 9)
    had: dict = {}
    peak = 0
    for _ in range(200):
        t.release_all_but([k for k in t.offset if rng.random() > 0.2])
        keys = {int(v) for v in rng.integers(0, 40, int(rng.integers(0, 6)))}
        for k in sorted(keys):
            if k not in t.offset and t.revive(k):
                assert t.offset[k] == had[k]
        wants = [(k, int(rng.choice(sizes))) for k in sorted(keys)]
        _put(t, wants)
        for k, n in wants:
            assert t.size_of[k] == n
        had = {**t.offset, **{k: t._idle[k] for k in t.idle}}
        spans = sorted((o, o + t.size_of[k]) for k, o in had.items())
        assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:], strict=False))
        assert all(a >= 0 and b <= t.capacity for a, b in spans)
        peak = max(peak, t.live_elements())
        assert t.capacity <= max(h * (peak + 5 * 9) + 1, t.cache)


def test_control_without_releases_the_buffer_follows_the_keys_ever_seen():
    """The former behaviour (no slot freed before a compaction) grows with every key seen: the
    bound above is what the releases buy."""
    t = SlotTable()
    for step in range(50):
        _put(t, [f"{step}a", f"{step}b"])
    assert len(t) == 100 and t.capacity >= 100  # vs 2 live at a time with releases


def test_a_batch_with_an_idle_key_is_refused_until_it_is_revived():
    """Placing ``x`` could evict idle ``y`` of the same batch, which would then find no slot:
    ``grow_to`` refuses such a batch (``TextureStore.write`` revives them first)."""
    t = SlotTable(headroom=1.0)
    _put(t, [("y", 2), ("z", 2)])
    t.release("y")
    with pytest.raises(ValueError, match=r"revive the idle keys \['y'\]"):
        t.grow_to([("x", 2), ("y", 2)])
    assert t.revive("y")
    assert _put(t, [("x", 2), ("y", 2)]) == [] and sorted(t.offset) == ["x", "y", "z"]
