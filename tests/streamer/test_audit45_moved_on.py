"""Audit 45 (streaming): a demand whose level the camera moved on from is forgotten.

``Loader.demanded`` holds the levels a frame lacked until they arrive. A level no longer
wanted (the camera moved on before it was read) never arrived, so its demand stayed, with its
first frame's due time: a later read of the level ahead of need (a revisit's prefetch) counted
as real-time and as late against a frame long gone. The planning thread now forgets those
demands where it lowers the wants (``Loader.forget_steps``), except for a level being read or
decoded (bytes read because a frame lacked them stay real-time) and a failing block's levels
(still a block a frame needed: ``failing_blocks_needed``).

Everything runs inline (``workers=0``: the plan and the reads on the test's thread, the same
every run). The positive controls switch each part of the rule off on the loader instance.
"""

from __future__ import annotations

import time

import pytest
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 8 x 10 blocks of 33 samples (k = 5), 10 m cells."""
    tmp = tmp_path_factory.mktemp("moved_on")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def _poses(store):
    """A pose ``here`` and one ``away`` at the other end of a flight over the store."""
    z0, z1 = store.meta.extra["value_range"]
    path = default_flythrough(store.grid, z0, z1, 60, 60.0, speed=600.0, viewport=(320, 240))
    return path[0], path[-1]


@pytest.fixture(scope="module")
def target(store):
    """A block ``here`` needs at a level >= 1 that nothing wants ``away`` (probe session, the
    same frames as the tests'), and that level."""
    here, away = _poses(store)
    with open_session(store, budget_mb=64, workers=0) as probe:
        f = probe.update(here, 0, wait=True)
        probe.update(away, 0)
        return next(
            (b, lv)
            for b, (_, lv) in sorted(f.blocks.items())
            if lv >= 1 and probe.cache.want(b)[0] < lv
        )


def _lack(s, b, lv) -> None:
    """Evict ``b``'s levels from ``lv`` up (as the cache's eviction drops them)."""
    with s.loader.cv:
        while s.cache.level(b) >= lv:
            s.cache.drop_level(b)


def _move_on(s, away) -> None:
    """What ``update(away)`` does to the wants, from inside a read: pin the levels ``away``
    needs and apply its plan (the planning thread's work)."""
    needed = s.planner.needed(away)
    with s.loader.cv:
        s._pin_and_queue(needed, camera=away)
        s._plans.pending = (away, None, set(needed))
    s._plans.plan()


# -- a level demanded, never read, the camera moved on; read ahead later ---------------------


def _read_ahead_later(store, target, keep_all: bool = False) -> tuple[int, int, int, int, bool]:
    """Frame 1 lacks ``target`` (loading nothing), frame 2 is ``away``; then the level is
    wanted ahead only (no pin) and read. ``keep_all``: the old rule (no demand forgotten).
    Returns the read's bytes real-time, prefetched and late, the level's bytes, and whether
    the demand was still held after frame 2."""
    here, away = _poses(store)
    b, lv = target
    with open_session(store, budget_mb=64, workers=0, inline_bytes_per_frame=0) as s:
        ld = s.loader
        if keep_all:
            ld.forget_steps = lambda chunk=64: iter(())
        s.update(here, 0, wait=True)
        _lack(s, b, lv)
        s.update(here, 0)  # lacks the level; reads nothing (no inline allowance)
        with ld.cv:
            assert (b, lv) in ld.demanded
            due = ld.due[(b, lv)]
        s.update(away, 0)
        with ld.cv:
            held = (b, lv) in ld.demanded
            assert s.cache.level(b) == lv - 1 and s.cache.want(b)[0] < lv
        time.sleep(max(0.0, due - time.monotonic()) + 0.02)  # that frame's due time is past
        with ld.cv:
            s.cache.set_wants({b: (lv, -1, 1.0)}, s.level_bytes)  # a revisit's prefetch
            ld.take_counts()
            ld.reschedule()
        ld.load_inline(None)
        with ld.cv:
            assert s.cache.level(b) == lv
            c = ld.take_counts()
            realtime, prefetched, late = c.realtime, c.prefetched, c.late
            assert set(ld.due) == set(ld.demanded)
        return realtime, prefetched, late, s.level_bytes[lv], held


def test_a_level_the_camera_moved_on_from_is_prefetched_when_read_ahead(store, target):
    realtime, prefetched, late, nbytes, held = _read_ahead_later(store, target)
    assert not held  # forgotten with its due time when the plan for ``away`` was applied
    assert (realtime, prefetched, late) == (0, nbytes, 0)


def test_positive_control_a_demand_kept_makes_the_read_ahead_real_time_and_late(store, target):
    realtime, prefetched, late, nbytes, held = _read_ahead_later(store, target, keep_all=True)
    assert held
    assert (realtime, prefetched, late) == (nbytes, 0, nbytes)


# -- a demanded level being read when the camera moves on -----------------------------------


def _moved_on_while_reading(
    store, target, forget_reads: bool = False
) -> tuple[int, int, int, bool]:
    """Frame 2 lacks ``target``; its read starts and, while it runs, the camera moves
    ``away`` (pins and plan). ``forget_reads``: the rule without its exception for reads
    under way. Returns frame 2's real-time and prefetched bytes, the level's bytes and
    whether the demand was still held once the plan for ``away`` was applied."""
    here, away = _poses(store)
    b, lv = target
    moved = []

    def hook(block, level):
        if (block, level) == (b, lv) and not moved:
            _move_on(s, away)
            with s.loader.cv:
                moved.append((b, lv) in s.loader.demanded)

    with open_session(store, budget_mb=64, workers=0, inline_bytes_per_frame=1) as s:
        ld = s.loader
        if forget_reads:
            ld.reading = lambda b, level: False
        s.update(here, 0, wait=True)
        _lack(s, b, lv)
        s._read_hook = hook
        f = s.update(here, 0)  # lacks the level; reads it (its first level read), moving on
        assert moved and s.cache.level(b) == lv
        with ld.cv:
            assert s.cache.want(b)[0] < lv and (b, lv) not in ld.demanded
        return f.stats.realtime_bytes, f.stats.prefetched_bytes, s.level_bytes[lv], moved[0]


def test_a_demanded_level_read_while_the_camera_moves_on_stays_real_time(store, target):
    realtime, prefetched, nbytes, held = _moved_on_while_reading(store, target)
    assert held and (realtime, prefetched) == (nbytes, 0)


def test_positive_control_forgetting_a_read_under_way_makes_it_prefetched(store, target):
    realtime, prefetched, nbytes, held = _moved_on_while_reading(store, target, forget_reads=True)
    assert not held and (realtime, prefetched) == (0, nbytes)


# -- a failing level a frame needed, the camera moved on ------------------------------------


def _failing_then_away(store, target, forget_failing: bool = False) -> tuple[dict, bool]:
    """Frames ``here`` wait for ``target``, whose reads all fail; then the camera moves
    ``away``. ``forget_failing``: the rule without its exception for failing blocks. Returns
    the summary and whether the level is still demanded."""
    here, away = _poses(store)
    b, lv = target

    def hook(block, level):
        if (block, level) == (b, lv):
            raise OSError(f"injected failure of block {block} level {level}")

    kw = {"retries": 2, "backoff_s": 0.001, "max_backoff_s": 0.002, "raise_on_failure": False}
    with open_session(store, budget_mb=64, workers=0, **kw) as s:
        ld = s.loader
        if forget_failing:
            ld.failing = lambda b: False
        s._read_hook = hook
        for _ in range(3):
            s.update(here, 0, wait=True)
        s.update(away, 0)
        with ld.cv:
            assert s.cache.level(b) == lv - 1 and s.cache.want(b)[0] < lv
            still = (b, lv) in ld.demanded
        return s.summary(), still


def test_a_failing_level_a_frame_needed_stays_needed_after_moving_on(store, target):
    end, still = _failing_then_away(store, target)
    assert end["failing_blocks"] == 1 and still
    assert end["failing_blocks_needed"] == 1


def test_positive_control_forgetting_failing_demands_hides_the_needed_block(store, target):
    end, still = _failing_then_away(store, target, forget_failing=True)
    assert end["failing_blocks"] == 1 and not still
    assert end["failing_blocks_needed"] == 0
