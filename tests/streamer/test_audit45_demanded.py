"""Audit 45 (streaming): ``Loader.demanded`` forgets a demand once its level arrives. It never
shrank: a level a frame lacked once counted as real-time on every later reload of it, even one
read ahead after an eviction (prefetched bytes under-reported on a flight that revisits
blocks), and the set grew through the flight. A level that never arrives (a read that keeps
failing) stays demanded: its block is still one a frame needed (``failing_blocks_needed``).

The positive controls put the old rule back by installing a demanded set whose ``discard``
does nothing (:class:`_NeverMet`): the loader's only way of forgetting a demand."""

from __future__ import annotations

import pytest
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 8 x 10 blocks of 33 samples (k = 5), 10 m cells."""
    tmp = tmp_path_factory.mktemp("demanded")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def cams(store, n):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=600.0, viewport=(320, 240))


class _Recording(set):
    """``Loader.demanded`` that also keeps every level marked in ``added`` and counts the
    marks of a level demanded before and met since (``again``)."""

    def __init__(self) -> None:
        super().__init__()
        self.added: set = set()
        self.again = 0

    def add(self, item) -> None:
        self.again += item in self.added and item not in self
        self.added.add(item)
        super().add(item)


class _NeverMet(_Recording):
    """The old rule, for the positive controls: a demand is never discarded."""

    def discard(self, item) -> None:
        pass


# -- (a) a level demanded once, evicted, read again ahead of need --------------------------


def _reload_ahead(store, demanded: _Recording, pin: bool) -> tuple[int, int, int, int]:
    """A frame lacks a block's level ``lv`` (>= 1) and waits for it; then the block is no
    longer pinned, only wanted ahead at ``lv`` (``pin``: pinned at ``lv`` by the current
    frame instead), its level ``lv`` is evicted (dropped as the cache's eviction drops it)
    and read again, inline. Returns the bytes of that read counted real-time and
    prefetched, the levels reloaded and the level's bytes."""
    with open_session(store, budget_mb=64, workers=0) as s:
        ld, cache = s.loader, s.cache
        ld.demanded = demanded
        f = s.update(cams(store, 2)[0], wait=True)
        b, lv = next(
            (b, lv)
            for b, (have, lv) in f.blocks.items()
            if 1 <= lv <= have and (b, lv) in demanded.added
        )
        with ld.cv:
            cache.set_wants({b: (lv, lv if pin else -1, 1.0)}, s.level_bytes)
            while cache.level(b) >= lv:
                cache.drop_level(b)
            ld.take_counts()
            ld.reschedule()
            reloaded = s.totals.reloaded_levels
        ld.load_inline(None)
        with ld.cv:
            assert cache.level(b) == lv
            c = ld.take_counts()
            realtime, prefetched = c.realtime, c.prefetched
            return realtime, prefetched, s.totals.reloaded_levels - reloaded, s.level_bytes[lv]


def test_a_level_read_again_ahead_after_an_eviction_counts_as_prefetched(store):
    """The frame's demand was met when the level first arrived: read again ahead of need,
    after an eviction, nothing lacks it and nothing pins it, so it is prefetched."""
    realtime, prefetched, reloaded, nbytes = _reload_ahead(store, _Recording(), pin=False)
    assert reloaded == 1
    assert (realtime, prefetched) == (0, nbytes)


def test_positive_control_a_demand_never_met_makes_the_reload_real_time(store):
    """The old rule: the demand of the first frame still counts, the reload is real-time."""
    realtime, prefetched, reloaded, nbytes = _reload_ahead(store, _NeverMet(), pin=False)
    assert reloaded == 1
    assert (realtime, prefetched) == (nbytes, 0)


def test_a_reload_the_current_frame_pins_is_still_real_time(store):
    """The quiet case: the same reload, pinned by the frame being made, is real-time."""
    realtime, prefetched, reloaded, nbytes = _reload_ahead(store, _Recording(), pin=True)
    assert reloaded == 1
    assert (realtime, prefetched) == (nbytes, 0)


# -- (b) a long flight that revisits blocks --------------------------------------------------


def _revisiting_flight(store, demanded: _Recording) -> dict:
    """There and back twice, loading inline under a budget that evicts (the same every run).
    After every frame: the demanded levels that are resident, and whether the due times
    cover exactly the demanded levels. Each arrival is recorded with whether a frame lacked
    the level since it last arrived or the frame being made pins it: the bytes neither
    lacked nor pinned are the prefetched ones."""
    there = cams(store, 60)
    out = {"resident": 0, "due_differs": 0, "expected_prefetched": 0, "ahead_reloads": 0}
    with open_session(store, budget_mb=0.065, workers=0, inline_bytes_per_frame=40_000) as s:
        ld, cache = s.loader, s.cache
        ld.demanded = demanded
        lacked: set = set()
        real_add, real_mark = cache.add_level, demanded.add
        loaded: set = set()

        def mark(item) -> None:
            lacked.add(item)
            real_mark(item)

        def add_level(b, level, values, *, reserved=False):
            added = real_add(b, level, values, reserved=reserved)
            if added:
                if (b, level) not in lacked and cache.want(b)[1] < level:
                    out["expected_prefetched"] += int(values.nbytes)
                    out["ahead_reloads"] += (b, level) in loaded
                lacked.discard((b, level))
                loaded.add((b, level))
            return added

        demanded.add, cache.add_level = mark, add_level
        for cam in (there + there[::-1]) * 2:
            s.update(cam, 1 / 60)
            with ld.cv:
                out["resident"] += sum(1 for b, lv in ld.demanded if lv <= cache.level(b))
                out["due_differs"] += set(ld.due) != set(ld.demanded)
        with ld.cv:
            out["pending"] = {(b, lv) for b, lv in ld.demanded if lv > cache.level(b)}
        out.update(s.summary())
        out["evicted"] = cache.evicted_bytes
    return out


def test_demanded_holds_only_the_levels_not_arrived_over_a_revisiting_flight(store):
    """Every demanded level is one not resident (pending: it cannot have arrived), after
    every frame of a flight that evicts and reloads levels and demands levels again; the
    due times are kept for the same levels. The prefetched bytes are those of the levels
    read while no frame lacked them and none pinned them, reloads read ahead included."""
    demanded = _Recording()
    out = _revisiting_flight(store, demanded)
    assert out["evicted"] > 0 and out["reloaded_levels"] > 0 and demanded.again > 0
    assert out["resident"] == 0 and out["due_differs"] == 0
    assert set(demanded) == out["pending"] and len(demanded) < len(demanded.added)
    assert out["ahead_reloads"] > 0
    assert out["prefetched_bytes"] == out["expected_prefetched"]


def test_positive_control_demands_never_met_pile_up_and_hide_prefetched_reloads(store):
    """The old rule: the set keeps every level ever demanded, resident ones included, and
    reloads read ahead count as real-time (fewer prefetched bytes than were read ahead)."""
    demanded = _NeverMet()
    out = _revisiting_flight(store, demanded)
    assert out["reloaded_levels"] > 0
    assert out["resident"] > 0 and set(demanded) == demanded.added
    assert out["prefetched_bytes"] < out["expected_prefetched"]


# -- (c) a level a frame needs that keeps failing ------------------------------------------


def _failing_flight(store, level_of, discard_on_failure: bool = False) -> tuple[dict, bool, int]:
    """Five waited frames of one pose, inline, the reads of one level of one block failing
    every time: ``level_of(session, frame)`` picks ``(block, level)`` from a probe flight of
    two frames. ``discard_on_failure``: the failed read also drops the level's demand (the
    positive control: a rule that lets any end of a read meet its demand). Returns the
    summary, whether the level is still demanded, and how many of the block's lower levels
    are."""
    cam = cams(store, 2)[0]
    with open_session(store, budget_mb=64, workers=0) as probe:
        probe.update(cam, wait=True)
        b, bad = level_of(probe, probe.update(cam))

    def hook(block, level):
        if (block, level) == (b, bad):
            if discard_on_failure:
                s.loader.demanded.discard((b, bad))
            raise OSError(f"injected failure of block {block} level {level}")

    kw = {"retries": 2, "backoff_s": 0.001, "max_backoff_s": 0.002, "raise_on_failure": False}
    with open_session(store, budget_mb=64, workers=0, **kw) as s:
        s._read_hook = hook
        s.loader.demanded = demanded = _Recording()
        for _ in range(5):
            s.update(cam, wait=True)
        end = s.summary()
        lower = sum(1 for lv in range(bad) if (b, lv) in demanded)
        assert s.cache.level(b) == bad - 1  # the coarser levels arrived, the failing one not
        assert all((b, lv) in demanded.added for lv in range(bad))  # (a frame lacked them)
        return end, (b, bad) in demanded, lower


def _needed_level(s, f):
    """A block the frame needs at a level >= 1, and that level."""
    return next((b, lv) for b, (_, lv) in sorted(f.blocks.items()) if lv >= 1)


def _ahead_level(s, f):
    """A block the frame needs, wanted ahead finer than its pin, and the level above it."""
    return next(
        (b, s.cache.want(b)[1] + 1)
        for b in sorted(f.blocks)
        if s.cache.want(b)[0] > s.cache.want(b)[1]
    )


def test_a_failing_level_a_frame_needs_stays_demanded_and_needed(store):
    """The block's coarser levels arrived (their demands met); the level the frames need
    never does, so it stays demanded and the block counts as one a frame needed."""
    end, still, lower = _failing_flight(store, _needed_level)
    assert end["failing_blocks"] == 1 and end["failed_blocks_ever"] == 1
    assert still and lower == 0
    assert end["failing_blocks_needed"] == 1


def test_positive_control_a_failed_read_that_met_its_demand_hides_the_needed_block(store):
    end, still, _ = _failing_flight(store, _needed_level, discard_on_failure=True)
    assert end["failing_blocks"] == 1
    assert not still and end["failing_blocks_needed"] == 0


def test_a_failing_level_read_only_ahead_is_not_one_a_frame_needed(store):
    """The frames' own levels of the block all arrived; only a finer level read ahead fails:
    no frame needed that level (the old rule, every demand kept, called the block needed)."""
    end, still, lower = _failing_flight(store, _ahead_level)
    assert end["failing_blocks"] == 1 and not still and lower == 0
    assert end["failing_blocks_needed"] == 0
