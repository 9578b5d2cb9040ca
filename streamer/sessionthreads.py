"""A session's threads: its loaders' pool and its planning thread, closed within a bound, and
what they raised re-raised on the caller's thread.

Closing tells the planning pool first (it ends while the loaders' reads are awaited), stops
the loader, and joins both for at most the time given; threads still running then — a read a
server never answers — are named (:attr:`SessionThreads.unfinished`), and a later close waits
for them again. A planning failure or a loader bug no call re-raised yet is raised by the
close (or logged, when the caller's own exception is already in flight). A change of the store
under the session is final: every later call raises it again.
"""

from __future__ import annotations

import logging
import time

from streamer.errors import StreamerError
from streamer.loader import Loader
from streamer.planthread import PlanThread
from tiler.errors import StoreChangedError

#: (the session's logger: its messages kept their name when this module was split from it)
log = logging.getLogger("streamer.session")


class SessionThreads:
    """The threads of one session (see module doc); state guarded by the loader's lock."""

    def __init__(self, loader: Loader, plans: PlanThread) -> None:
        self.loader = loader
        self.plans = plans
        self.closed = False
        self.fatal_raised = False  # the store change was raised to the caller once
        self.unfinished: list[str] = []  # threads still running when close() returned

    def close(self, timeout_s: float, *, raise_bug: bool) -> list[str]:
        """Stop the threads, waiting at most ``timeout_s``; the names of those still running.
        ``raise_bug``: raise a background failure not raised yet (else it is logged)."""
        with self.loader.cv:
            again = self.closed
            self.closed = self.plans.closed = True
        if again:  # (it returned [] while the threads the first close named still ran)
            return self.join_left(timeout_s)
        t0 = time.monotonic()
        pool = self.plans.pool
        if pool is not None:  # told first: it ends while the loader's reads are awaited
            pool.shutdown(wait=False, cancel_futures=True)
        alive = self.loader.close(timeout_s)
        if pool is not None:
            for t in pool.threads:
                t.join(timeout=max(0.0, timeout_s - (time.monotonic() - t0)))
                if t.is_alive():
                    alive.append(t.name)
        if alive:
            log.warning("session threads still running after %.1f s: %s", timeout_s, alive)
        self.unfinished = alive
        if raise_bug:
            self.raise_error(fatal=not self.fatal_raised)
        else:
            with self.loader.cv:
                left = self.plans.error or self.loader.bug
            if left is not None:
                log.error("a session thread failed: %r", left)
        return alive

    def join_left(self, timeout_s: float) -> list[str]:
        """Wait at most ``timeout_s`` for the threads still running after a close; the names
        of those still running then (kept as :attr:`unfinished`)."""
        pool = self.plans.pool
        threads = self.loader.threads() + ([] if pool is None else pool.threads)
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        for t in threads:
            if t.is_alive():
                t.join(timeout=max(0.0, deadline - time.monotonic()))
        self.unfinished = [t.name for t in threads if t.is_alive()]
        return list(self.unfinished)

    def raise_error(self, *, fatal: bool = True) -> None:
        """Re-raise a planning failure or a loader bug on the caller's thread, and (``fatal``)
        a change of the store under the session, which every later call raises again."""
        ld, plans = self.loader, self.plans
        if plans.error is None and ld.bug is None and (not fatal or ld.fatal is None):
            return  # (read without the lock: one set meanwhile is raised by the next call)
        with ld.cv:
            plan_exc, plans.error = plans.error, None
            bug, ld.bug = ld.bug, None
            changed = ld.fatal if fatal else None
        if plan_exc is not None:
            raise StreamerError(f"prefetch planning failed: {plan_exc}") from plan_exc
        if bug is not None:
            raise bug
        if changed is not None:
            self.fatal_raised = True
            raise StoreChangedError(
                f"{changed}; the session stopped loading when it saw the change (a remote "
                "store's levels read in the second before may be the new store's)"
            ) from changed
