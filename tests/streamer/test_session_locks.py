"""The session's lock discipline (issue 14): the caller's thread only plans (no read, no
decode), and no thread reads, decodes or plans while holding the lock ``update()`` waits on;
holds are recorded by :mod:`streamer.lockprobe`. The positive control is a loader that reads
while holding the lock."""

from __future__ import annotations

import time

import pytest
from demtools import fractal, write_dem

from streamer.lockprobe import install
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("locks")
    src = write_dem(tmp / "d.tif", fractal((257, 385), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=2))


@pytest.fixture(scope="module")
def store33(tmp_path_factory):
    """The same DEM in blocks of 33² (96 blocks: more cache entries than a plan's step)."""
    tmp = tmp_path_factory.mktemp("locks33")
    src = write_dem(tmp / "d.tif", fractal((257, 385), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=2))


def _fly(s, store, probe, frames: int = 150, wait_every: int = 10) -> None:
    z0, z1 = store.meta.extra["value_range"]
    cams = default_flythrough(store.grid, z0, z1, frames, 60.0, viewport=(320, 240))
    s.warm_up(cams[0])  # (plans the prefetch on the caller's thread, as documented)
    probe.calls.clear()
    for i, cam in enumerate(cams):
        s.update(cam, 1 / 60, wait=i % wait_every == 0)  # some frames wait on the condition


def test_no_read_decode_or_planning_under_the_lock(store):
    with open_session(store, budget_mb=4, workers=3) as s:
        probe = install(s)
        _fly(s, store, probe)
        roles = probe.by_role()
    assert probe.violations == []
    what = {w for _, w in probe.calls}
    assert {"read_level_raw", "decode_next", "planner.needed", "planner.prefetch"} <= what
    by_caller = {w for name, w in probe.calls if name == "MainThread"}
    assert by_caller == {"planner.needed"}  # update() plans the visible set, nothing else
    assert len(roles["caller"]) > 150 and len(roles["loader"]) > 50 and roles["planner"]


def test_positive_control_a_loader_reading_under_the_lock_is_caught(store):
    with open_session(store, budget_mb=4, workers=3) as s:
        probe = install(s)
        read = s.store.read_level_raw  # the probed read

        def slow_read(b, level):
            with s.loader.cv:  # a loader that holds the session lock while it reads
                time.sleep(0.002)
                return read(b, level)

        s.store.read_level_raw = slow_read
        _fly(s, store, probe, frames=30)
        roles = probe.by_role()
    assert probe.violations and {w for _, w in probe.violations} == {"read_level_raw"}
    assert all(name.startswith("terrastream-load") for name, _ in probe.violations)
    assert max(wall for wall, _ in roles["loader"]) >= 0.002  # the sleep is inside a hold


def _one_hold_pump(self) -> None:
    """The pump before (0fda539): every job of a call taken in one hold of the lock."""
    if self._pool is None:
        return
    with self.cv:
        jobs = []
        while (
            not self.closed
            and self.bug is None
            and self.fatal is None
            and (self._in_flight < self.config.workers)
        ):
            job = self.next_job()
            if job is None:
                break
            self._in_flight += 1
            jobs.append(job)
    for job in jobs:
        self._pool.submit(self.run_job, job).add_done_callback(self._done)


def _takes_per_hold(store, pump=None) -> list[list[int]]:
    """For each ``pump`` call that took two jobs or more: the lock holds released before each
    take (equal numbers: taken in one hold)."""
    import threading
    import types

    with open_session(store, budget_mb=4, workers=3) as s:
        probe = install(s)
        ld, local, calls = s.loader, threading.local(), []
        if pump is not None:
            ld.pump = types.MethodType(pump, ld)
        real_pump, real_next = ld.pump, ld.next_job

        def pumping():  # (a pump may run inside another: a job done before its callback)
            outer, local.seen = getattr(local, "seen", None), []
            try:
                real_pump()
            finally:
                calls.append(local.seen)
                local.seen = outer

        def next_job(*a, **k):
            job = real_next(*a, **k)
            if job is not None and getattr(local, "seen", None) is not None:
                local.seen.append(len(probe.holds))
            return job

        real_done = ld._done

        def done(fut):  # (its own take, when a job ends before its callback is attached,
            outer, local.seen = getattr(local, "seen", None), None  # is not the pump's)
            try:
                real_done(fut)
            finally:
                local.seen = outer

        ld.pump, ld.next_job, ld._done = pumping, next_job, done
        _fly(s, store, probe, frames=40)
    return [c for c in calls if len(c) >= 2]


def test_a_pump_takes_each_job_in_its_own_hold(store):
    many = _takes_per_hold(store)
    assert many  # pumps that took several jobs happened
    assert all(a < b for c in many for a, b in zip(c, c[1:], strict=False)), many


def test_positive_control_a_pump_taking_its_jobs_in_one_hold_is_caught(store):
    many = _takes_per_hold(store, _one_hold_pump)
    assert many and all(len(set(c)) == 1 for c in many), many


def _one_hold_trim_plan(self) -> None:
    """``PlanThread.plan`` with its trim's steps all taken in one hold of the lock (as at
    07bf328, where one ``trim`` call walked every entry)."""
    from streamer.planthread import PLAN_STEP_BLOCKS

    ld = self.loader
    with ld.cv:
        req, self.pending = self.pending, None
    if req is None:
        return
    plan = self.planner.prefetch(*req)
    cfg = ld.config
    self.stepwise(ld.cache.prefetch_steps(plan.wants, PLAN_STEP_BLOCKS))
    with ld.cv:
        for _ in ld.cache.trim_steps(int(cfg.linger_s * cfg.fps), PLAN_STEP_BLOCKS):
            pass
        self.ring = plan.ring
    self.stepwise(ld.reschedule_steps(PLAN_STEP_BLOCKS))
    ld.pump()


def _trim_steps_per_hold(store, plan=None) -> tuple[list[list[int]], list[int], int]:
    """Fly with ``linger_s=0`` (every level the frame does not want is unloaded by the planning
    thread): for each trim, the lock holds released before each of its steps; each trim's
    step size; the bytes trimmed."""
    import types

    from streamer.planthread import PlanThread

    with open_session(store, budget_mb=4, workers=3, linger_s=0.0) as s:
        probe = install(s)
        cache, trims, chunks, trimmed = s.loader.cache, [], [], [0]
        real = cache.trim_steps
        if plan is not None:
            s._plans.plan = types.MethodType(plan, s._plans)
        assert isinstance(s._plans, PlanThread)

        def trim_steps(linger_frames=0, chunk=64):
            seen = []
            trims.append(seen)
            chunks.append(chunk)
            for n in real(linger_frames, chunk):
                seen.append(len(probe.holds))
                trimmed[0] += n
                yield n

        cache.trim_steps = trim_steps
        # every frame waits for its loads, so levels the camera leaves behind are resident
        # and get trimmed (unpaced, a loaded machine's loaders could leave none: nothing
        # trimmed, a flaky control)
        _fly(s, store, probe, frames=60, wait_every=1)
    return [t for t in trims if len(t) >= 2], chunks, trimmed[0]


def test_the_planning_thread_trims_in_short_holds(store33):
    """With ``linger_s`` set, the planning thread unloads what lingered ``PLAN_STEP_BLOCKS``
    blocks per hold of the lock (one hold walked every entry and dropped every stale level:
    up to 2.7 ms of CPU on a 64×64-block store)."""
    from streamer.planthread import PLAN_STEP_BLOCKS

    many, chunks, trimmed = _trim_steps_per_hold(store33)
    assert trimmed > 0 and many  # levels were unloaded, by trims of several steps
    assert set(chunks) == {PLAN_STEP_BLOCKS}
    assert all(a < b for t in many for a, b in zip(t, t[1:], strict=False)), many


def test_positive_control_a_trim_in_one_hold_is_caught(store33):
    many, _, trimmed = _trim_steps_per_hold(store33, _one_hold_trim_plan)
    assert trimmed > 0 and many and all(len(set(t)) == 1 for t in many), many


def _rescheduled_keys(store, reschedule=None) -> tuple[int, int]:
    """Fly with ``workers=0`` loading a little a frame (the cache holds a plan's wants, pins
    and priorities; many blocks short of them), stop mid-flight, rebuild the queue
    (``reschedule(loader)``, else ``Loader.reschedule``); how many queued blocks have the
    key :meth:`Loader.key` gives them, of how many."""
    with open_session(store, budget_mb=4, workers=0, inline_bytes_per_frame=1) as s:
        z0, z1 = store.meta.extra["value_range"]
        cams = default_flythrough(store.grid, z0, z1, 40, 60.0, viewport=(320, 240))
        for cam in cams:
            s.update(cam, 1 / 60)
        ld = s.loader
        with ld.cv:
            if reschedule is None:
                ld.reschedule()
            else:
                reschedule(ld)
            queued = ld.queue.blocks()
            same = sum(ld.queue.queued_key(b) == ld.key(b) for b in queued)
    return same, len(queued)


def test_the_rebuild_keys_the_blocks_as_the_loader_does(store33):
    """The queue's rebuild keys each short block from the values the cache's walk read
    (no second look-up per block): the keys are :meth:`Loader.key`'s."""
    same, n = _rescheduled_keys(store33)
    assert n > 10 and same == n


def test_positive_control_a_rebuild_with_other_keys_is_caught(store33):
    """A rebuild that keys by the priority without its sign (far blocks first) and ignores
    the pins is told apart by the same comparison."""

    def wrong(ld) -> None:
        items = [((0 if b not in ld.errors else 1, 0, ld.cache.level(b) + 1, p, b), b)
                 for part in ld.cache.short_steps() for b, _w, _pin, p in part]  # fmt: skip
        ld.queue.rebuild(items, time.monotonic())

    same, n = _rescheduled_keys(store33, wrong)
    assert n > 10 and same < n


def _caller_holds_per_frame(store, extra_hold: bool = False) -> tuple[int, int]:
    """Fly 60 frames with 2 loaders: the caller's holds of the lock in ``update`` and the
    frames. ``extra_hold``: the background errors looked for under the lock and the pose
    posted in a hold of its own (as before)."""
    with open_session(store, budget_mb=4, workers=2) as s:
        probe = install(s)
        if extra_hold:
            real_raise, real_post = s._raise_background_error, s._plans.post

            def raise_bug(**kw):
                with s._cv:
                    pass
                real_raise(**kw)

            def post(*a):
                s._cv.release()  # (called under the update's hold: released and re-taken)
                try:
                    with s._cv:
                        pass
                finally:
                    s._cv.acquire()
                return real_post(*a)

            s._raise_background_error, s._plans.post = raise_bug, post
        z0, z1 = store.meta.extra["value_range"]
        cams = default_flythrough(store.grid, z0, z1, 60, 60.0, viewport=(320, 240))
        s.warm_up(cams[0])
        probe.clear()
        for cam in cams:
            s.update(cam, 1 / 60)
        roles = probe.by_role()
    return len(roles["caller"]), len(cams)


def test_update_takes_the_lock_at_most_four_times_a_frame(store33):
    """A hold that finds the lock taken costs its thread a GIL hand-off too (~0.1–1 ms), so
    ``update`` takes it few times: its pins with the pose for the planning thread, at most
    one job take (none while every loader is busy), two for the frame's report; the
    background errors are looked for without it (six holds a frame before)."""
    caller_holds, frames = _caller_holds_per_frame(store33)
    assert caller_holds <= 4 * frames, (caller_holds, frames)


def test_positive_control_two_more_holds_a_frame_are_caught(store33):
    caller_holds, frames = _caller_holds_per_frame(store33, True)
    assert caller_holds > 4 * frames, (caller_holds, frames)
