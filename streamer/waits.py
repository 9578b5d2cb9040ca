"""How a session's caller waits for its loads: the warm-up's wait for an idle loader and
``update(wait=True)``'s wait for a frame's levels, both bounded, both ended at once by a loader
bug, both sleeping until the next retry is due or a load finishes (the loader's condition).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from streamer.cache import Block
from streamer.errors import LoadError, SessionClosedError
from streamer.frames import SessionConfig
from streamer.loader import Loader
from streamer.loadreport import describe_missing, stuck

#: what a wait that timed out suggests besides the server (the CLI has no such option: "")
MORE_TIME = {"more_time": ", or allow more time (warm_up's timeout_s, wait_timeout_s)"}
#: a waiter that queued refused levels again pumps at least this often (s): the room they
#: wait for can free without a notify (an eviction by the planning thread)
REQUEUE_NAP_S = 0.05


def wait_idle(
    ld: Loader, raise_bug: Callable[[], None], deadline: float, limit: float, start: float
) -> None:
    """Wait until ``ld`` has nothing queued or running but failed blocks in backoff and blocks
    whose reads failed ``retries`` times since ``start`` (a server that fails slowly, e.g. by
    timing out, keeps a retry running: it no longer holds the wait to its deadline), pumping
    for retries; ``LoadError`` at ``deadline`` (``limit``: the seconds it allowed). The
    warm-up calls it inside :func:`waiting` for its whole span (between its passes too)."""
    while True:
        raise_bug()  # a loader bug ends the wait with its cause
        closed_meanwhile(ld)
        ld.pump()
        with ld.cv:
            now = time.monotonic()
            pending = ld.busy() and not only_backoff(ld, now) and not only_given_up(ld, start)
            if not pending:
                return
            left = deadline - now
            if left <= 0:
                raise LoadError(
                    "warm-up did not finish within {limit:.1f} s ({state}): check the "
                    "store's server{more_time}",
                    params=MORE_TIME,
                    limit=limit,
                    state=stuck(ld),
                )
            ld.cv.wait(timeout=nap(ld, left, now))


@contextmanager
def waiting(ld: Loader, since: float) -> Iterator[None]:
    """Inside, the load queue leaves untried the failed blocks that gave up since ``since``
    (``LoadQueue.waiting_since``): the wait no longer waits for them, and retrying them kept
    a worker from the blocks it did wait for; they are retried again (healing) after it."""
    with ld.cv:
        ld.queue.waiting_since = since
    try:
        yield
    finally:
        with ld.cv:
            ld.queue.waiting_since = None


def closed_meanwhile(ld: Loader) -> None:
    """Raise :class:`SessionClosedError` when another thread closed the session during a wait
    (``Loader.close`` wakes the waiter)."""
    if ld.closed:
        raise SessionClosedError("the session was closed by another thread while this call waited")


def only_backoff(ld: Loader, now: float) -> bool:
    """Nothing runs and every queued block waits for a retry of a failed read (caller holds
    the lock)."""
    q = ld.queue
    return (
        not ld.decoding
        and not any(ld.fetching.values())
        and all(q.is_failed(b) for b in q.retry_at)
        and q.next_retry(now) is not None
    )


def only_given_up(ld: Loader, since: float) -> bool:
    """Every block queued, being read or decoded has failed ``retries`` reads since ``since``
    (caller holds the lock): waiting longer only waits for more failures."""
    q = ld.queue
    pending = q.blocks() | ld.decoding
    pending.update(b for b, levels in ld.fetching.items() if levels)
    return bool(pending) and all(q.given_up(b, since) for b in pending)


def nap(ld: Loader, left: float, now: float) -> float:
    """How long a waiter sleeps: until the next retry is due, at most ``left``."""
    nxt = ld.queue.next_retry(now)
    return max(1e-4, min(left, nxt if nxt is not None else left))


def wait_for(
    ld: Loader,
    cfg: SessionConfig,
    raise_bug: Callable[[], None],
    needed: dict[Block, int],
    due: float,
) -> None:
    """Wait until every block of ``needed`` is loaded or failed (``Session.update``'s
    ``wait=True``; ``due``: the frame's due time, for the late-bytes count). Blocks that gave
    up since the wait began are not retried meanwhile (:func:`waiting`)."""
    ld.mark_demand(needed, due)
    start = time.monotonic()
    deadline = start + cfg.wait_timeout_s
    q = ld.queue
    with waiting(ld, start):
        while True:
            raise_bug()  # a loader bug ends the wait with its cause
            closed_meanwhile(ld)
            more = False  # inline: a retry is due already (the pass stopped at it)
            if cfg.workers == 0:
                more = ld.load_inline(None, deadline)
            else:
                ld.pump()
            with ld.cv:
                now = time.monotonic()
                missing = [(b, lv) for b, lv in ld.missing(needed) if not q.given_up(b, start)]
                if not missing:
                    return
                if cfg.raise_on_failure and ld.unreported:
                    return  # a block failed every retry: the frame raises, more waiting delays it
                if cfg.workers == 0 and not more and not q.next_retry(now):
                    return  # nothing more can load inline
                left = deadline - now
                if left <= 0:
                    raise LoadError(
                        "{n} visible block level(s) did not load within {limit:.1f} s "
                        "({state}): check the store's server{more_time}",
                        params=MORE_TIME,
                        n=len(missing),
                        limit=cfg.wait_timeout_s,
                        state=describe_missing(ld, missing, now),
                    )
                sleep = nap(ld, left, now)
                if cfg.workers:
                    if ld.requeue_idle(missing):
                        sleep = min(sleep, REQUEUE_NAP_S)  # room may free without a notify
                    ld.cv.wait(timeout=sleep)
                    continue
            if not more:
                time.sleep(sleep)
