"""The caller's per-frame bookkeeping stays small (issue 14): a visible block that lacks a level
is queued once, not once per frame, and a block shown as on the previous frame is not marked
again, with the same demanded/due/used records as marking every block every frame (the marks
recorded as they are made: the loader forgets a demand once its level arrives)."""

from __future__ import annotations

import sys

import pytest
from demtools import fractal, write_dem

from streamer.loadqueue import LoadQueue
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("caller")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def cams(store, n):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=600.0, viewport=(320, 240))


def test_queue_keeps_one_entry_per_block_and_key():
    q = LoadQueue(retries=3, backoff_s=0.1, max_backoff_s=1.0)
    b = (2, 3)
    q.push(b, (1, 0, 2))
    q.push(b, (1, 0, 2))  # the same key again: not queued twice
    q.push(b, (1, 1, 5))  # less urgent: not queued
    assert len(q) == 1 and q.queued_key(b) == (1, 0, 2)
    q.push(b, (0, 0, 0))  # more urgent: queued, and it is what pops first
    assert len(q) == 2 and q.queued_key(b) == (0, 0, 0)
    assert q.pop(0.0, lambda blk: "job") == (b, "job")
    assert q.queued_key(b) is None  # popped: pushing it again queues it
    q.push(b, (1, 1, 5))
    assert q.queued_key(b) == (1, 1, 5)
    q.rebuild([((3,), b), ((2,), (0, 0))])
    assert q.queued_key(b) == (3,) and q.queued_key((0, 0)) == (2,)
    q.clear()
    assert q.queued_key(b) is None and len(q) == 0


def _fly_stalling(store, s, n=120):
    """An unpaced flight that outruns one slow loader: visible blocks lack levels for many
    frames in a row. Returns the largest queue length seen after an update."""
    longest = 0
    for cam in cams(store, n):
        s.update(cam, 1 / 60)
        longest = max(longest, len(s.loader.queue))
    return longest


def test_a_stalled_visible_block_is_queued_once(store):
    blocks = store.grid.rows * store.grid.cols
    with open_session(store, budget_mb=16, workers=1, latency_ms=5) as s:
        longest = _fly_stalling(store, s)
        stalls = s.summary()["stall_frames"]
    assert stalls > 20, "the flight must stall for the test to mean anything"
    assert longest <= 2 * blocks  # a key per block (a pinned and a prefetch one at most)


def test_positive_control_a_queue_without_the_check_grows_every_frame(store, monkeypatch):
    """The same flight with the old push (every call queued): the heap outgrows the bound."""
    import heapq

    def push_always(self, b, key):
        if self.retryable(b):
            heapq.heappush(self._heap, (key, b))
            self._best[b] = key if b not in self._best else min(key, self._best[b])

    monkeypatch.setattr(LoadQueue, "push", push_always)
    monkeypatch.setattr(LoadQueue, "queued_key", lambda self, b: None)
    blocks = store.grid.rows * store.grid.cols
    with open_session(store, budget_mb=16, workers=1, latency_ms=5) as s:
        longest = _fly_stalling(store, s)
    assert longest > 2 * blocks


def _marks(frames):
    """What marking every block of every frame records: demanded ``(block, level)``s and each
    block's finest level drawn."""
    demanded, used = set(), {}
    for f in frames:
        for b, (have, lv) in f.blocks.items():
            demanded.update((b, lvl) for lvl in range(have + 1, lv + 1))
            if min(have, lv) > used.get(b, -1):
                used[b] = min(have, lv)
    return demanded, used


class _Recording(set):
    """``Loader.demanded`` that also keeps every level ever marked in ``added``: the loader
    discards a demand when its level arrives, so the set itself holds only the pending ones."""

    def __init__(self) -> None:
        super().__init__()
        self.added: set = set()

    def add(self, item) -> None:
        self.added.add(item)
        super().add(item)

    def update(self, *others) -> None:  # (no marker uses it; recorded all the same)
        for other in others:
            for item in other:
                self.add(item)


def _threaded_flight(store, liar=False):
    """Frame 0 waits (its levels are resident: something is drawn), the rest outrun one
    loader. Returns the frames, the demanded levels marked by frame 0's wait, and the
    demanded levels marked over the whole flight and the drawn levels at the end."""
    with open_session(store, budget_mb=16, workers=1, latency_ms=1) as s:
        s.loader.demanded = marks = _Recording()
        frames = []
        for i, cam in enumerate(cams(store, 150)):
            if liar:  # every block claims the previous frame's state: nothing is marked
                s._shown = _SameAsAnything()
            frames.append(s.update(cam, 1 / 60, wait=i == 0))
            if i == 0:
                waited = set(marks.added)
        assert s.loader.demanded is marks  # (not replaced: every mark was recorded)
        return frames, waited, set(marks.added), dict(s.totals.used), s.summary()


class _SameAsAnything(dict):
    def get(self, key, default=None):
        return _Equal()


class _Equal:
    def __eq__(self, other: object) -> bool:
        return True

    __hash__ = None  # type: ignore[assignment]


def test_skipping_unchanged_blocks_records_what_marking_all_of_them_does(store):
    frames, waited, demanded, used, summary = _threaded_flight(store)
    assert summary["stall_frames"] > 10  # blocks lack levels over several frames in a row
    ref_demanded, ref_used = _marks(frames)
    assert ref_used and ref_demanded - waited
    assert demanded == waited | ref_demanded
    assert used == ref_used


def test_positive_control_skipping_every_block_loses_the_marks(store):
    frames, waited, demanded, used, _ = _threaded_flight(store, liar=True)
    ref_demanded, ref_used = _marks(frames)
    assert demanded == waited and ref_demanded - waited  # the later frames' marks are lost
    assert ref_used and not used


def _stale_reads(s, *, also_level: bool) -> None:
    """Make the frame's first read of the resident levels one level behind the cache for the
    blocks whose level changed, as when their newest level arrives between the frame's two
    holds of the lock (then it counts as a change for the next frame too). ``also_level``:
    the frame's re-read in the second hold too, the positive control; the loader's reads
    stay true."""
    cache = s.cache
    real_take, real_level = cache.take_level_changes, cache.level

    def take():
        moved = real_take()
        cache._moved.update(b for b, top in moved.items() if top >= 0)  # (seen again next)
        return {b: top - 1 if top >= 0 else top for b, top in moved.items()}

    cache.take_level_changes = take
    if also_level:

        def level(b):
            stale = sys._getframe(1).f_code.co_name == "_finish_frame"
            return max(-1, real_level(b) - 1) if stale else real_level(b)

        cache.level = level


def _late_marks(store, also_level: bool) -> tuple[int, int, int]:
    """Fly loading a few levels inline per frame (no thread: the same every run), the first
    reads stale from frame 5; count the blocks the frames show lacking a level the cache holds
    and the demanded levels that were resident when marked (due entries of resident levels)."""
    behind = stale_due = marked = 0
    with open_session(store, budget_mb=16, workers=0, inline_bytes_per_frame=20_000) as s:
        level = s.cache.level
        for i, cam in enumerate(cams(store, 40)):
            if i == 5:
                _stale_reads(s, also_level=also_level)
            before = set(s.loader.due)
            f = s.update(cam, 1 / 60)
            behind += sum(have < min(lv, level(b)) for b, (have, lv) in f.blocks.items())
            new = set(s.loader.due) - before
            marked += len(new)
            stale_due += sum(lvl <= level(b) for b, lvl in new)
    return behind, stale_due, marked


def test_a_level_that_arrives_between_the_frame_holds_is_shown_not_marked(store):
    """The frame reads the resident levels in one short hold, finds the blocks that changed
    without the lock, and marks their missing levels in a second hold, where a level that
    arrived in between is shown, not marked as demanded."""
    behind, stale_due, marked = _late_marks(store, also_level=False)
    assert marked > 0  # levels were missing and marked in the flight
    assert behind == 0 and stale_due == 0


def test_positive_control_marks_from_the_first_read_alone_are_stale(store):
    behind, stale_due, _ = _late_marks(store, also_level=True)
    assert behind > 0 and stale_due > 0


def _mirror_misses(store, forget_drops: bool) -> tuple[int, int]:
    """Fly under a budget that evicts, loading inline (nothing changes after ``update``
    returns); count the frames whose copy of the resident levels differs from the cache's
    and the levels evicted (``forget_drops``: a drop not recorded as a change, the control)."""
    misses = 0
    with open_session(store, budget_mb=0.065, workers=0, inline_bytes_per_frame=40_000) as s:
        if forget_drops:
            real_drop = s.cache.drop_level

            def drop(block):
                moved = set(s.cache._moved)
                real_drop(block)
                s.cache._moved = moved

            s.cache.drop_level = drop
        for cam in cams(store, 60):
            s.update(cam, 1 / 60)
            misses += s._resident != dict(s.cache._top)
        return misses, s.cache.evicted_bytes


def test_the_callers_copy_of_the_resident_levels_is_the_caches(store):
    """The frame reads the resident levels from its own copy, kept from the changes since
    the previous frame (``LevelCache.take_level_changes``): after every frame of a flight
    that loads and evicts, the copy is the cache's."""
    misses, evicted = _mirror_misses(store, forget_drops=False)
    assert evicted > 0 and misses == 0


def test_positive_control_a_drop_not_recorded_leaves_the_copy_stale(store):
    misses, evicted = _mirror_misses(store, forget_drops=True)
    assert evicted > 0 and misses > 0


def test_update_from_two_threads_at_once_is_refused(store):
    """Two threads inside ``update`` at once shared its frame state unnoticed (the previous
    camera, the pins, the frame count); the second is now refused, naming the rule. The
    control: the same two threads taking turns both get their frames."""
    import threading

    from streamer.errors import SessionThreadError

    c = cams(store, 2)
    inside, go_on = threading.Event(), threading.Event()
    with open_session(store, budget_mb=64, workers=0) as s:
        plan = s.planner.needed_arrays

        def slow_plan(cam):
            inside.set()
            assert go_on.wait(10)
            return plan(cam)

        s.planner.needed_arrays = slow_plan
        first = threading.Thread(target=s.update, args=(c[0],), name="first-caller")
        first.start()
        assert inside.wait(10)
        with pytest.raises(SessionThreadError, match="another thread is inside it"):
            s.update(c[1])
        go_on.set()
        first.join(10)
        assert not first.is_alive()
        s.planner.needed_arrays = plan
        turn = threading.Thread(target=s.update, args=(c[1],), name="second-caller")
        turn.start()
        turn.join(10)
        s.update(c[0])
        assert s.summary()["frames"] == 3
