"""A session's planning thread: the prefetch plan for the latest pose, applied to the cache
and the load queue in short locked steps.

The caller posts each frame's pose (:meth:`PlanThread.request`); one thread of a
``terrastream-plan`` pool plans the latest one posted (older ones are skipped), with no lock
held while it plans, then writes the plan's wants into the cache, unloads what lingered too
long (``linger_s``) and rebuilds the load queue, ``PLAN_STEP_BLOCKS`` blocks at a time,
releasing the loader's lock between the steps so that ``update()`` and the loaders never wait
long for it. Without workers there is no thread: the session calls :meth:`PlanThread.plan`
itself. A planning failure is kept in :attr:`error` for the session to raise on the caller's
thread.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from concurrent.futures import Future
from typing import Any

from streamer.cache import Block
from streamer.camera import Camera
from streamer.loader import Loader
from streamer.planner import Planner
from streamer.pool import DaemonPool

#: blocks per locked step of the planning thread (prefetch wants, queue rebuild): a step of 64
#: held the lock 27 / 158 µs CPU (p50 / p99, bench/session_update.py --locks); 16 keeps the
#: loaders' and the caller's waits for it to a few tens of µs
PLAN_STEP_BLOCKS = 16
_DONE = object()


class PlanThread:
    """The prefetch planning of one session (see module doc); state guarded by the loader's
    lock."""

    def __init__(self, planner: Planner, loader: Loader, workers: int) -> None:
        self.planner = planner
        self.loader = loader
        self.pending: tuple[Camera, Any, Collection[Block]] | None = None  # the latest pose
        self.running = False  # a plan loop is submitted or running
        self.closed = False
        self.error: BaseException | None = None  # a planning failure not raised yet
        self.ring = 0  # |N - M| of the latest plan
        self.pool = DaemonPool(1, "terrastream-plan") if workers else None

    def plan(self) -> None:
        """Plan the pending pose, if any, and apply the plan (the cache's wants, the queue)."""
        ld = self.loader
        with ld.cv:
            req, self.pending = self.pending, None
        if req is None:
            return
        camera, velocity, visible = req
        plan = self.planner.prefetch(camera, velocity, visible)  # no lock held
        cfg = ld.config
        self.stepwise(ld.cache.prefetch_steps(plan.wants, PLAN_STEP_BLOCKS))
        if cfg.linger_s is not None:
            self.stepwise(ld.cache.trim_steps(int(cfg.linger_s * cfg.fps), PLAN_STEP_BLOCKS))
        with ld.cv:
            self.ring = plan.ring
        self.stepwise(ld.reschedule_steps(PLAN_STEP_BLOCKS))
        ld.pump()

    def stepwise(self, steps: Iterator[None]) -> None:
        """Run a generator's steps, each under the loader's lock."""
        while True:
            with self.loader.cv:
                if next(steps, _DONE) is _DONE:
                    return

    def request(self, camera: Camera, velocity: Any, visible: Collection[Block]) -> None:
        """Post a pose; the thread plans it (or a later one) soon (no thread: see :meth:`plan`)."""
        with self.loader.cv:
            start = self.post(camera, velocity, visible)
        if start:
            self.start()

    def post(self, camera: Camera, velocity: Any, visible: Collection[Block]) -> bool:
        """:meth:`request`'s part under the loader's lock (the caller holds it, e.g. in the
        hold that pins its frame); True when :meth:`start` must be called after it."""
        self.pending = (camera, velocity, visible)
        if self.pool is None or self.running:
            return False
        self.running = True
        return True

    def start(self) -> None:
        """Start the planning loop (after :meth:`post` said so; no lock held)."""
        assert self.pool is not None
        self.pool.submit(self._loop).add_done_callback(self._done)

    def _loop(self) -> None:
        while True:
            self.plan()
            with self.loader.cv:
                if self.pending is None or self.closed:
                    self.running = False
                    return

    def _done(self, fut: Future) -> None:
        exc = None if fut.cancelled() else fut.exception()
        if exc is not None:
            with self.loader.cv:
                self.running = False
                self.error = exc
