"""A fixed pool of named daemon threads, for work that may block in a read no one answers.

``concurrent.futures.ThreadPoolExecutor`` joins every worker thread at interpreter exit, so a
Python program whose session had a read hanging on a stalled server waited out that read's
timeout (30 s by default) after its last line, closed session or not. :class:`DaemonPool` has
the same ``submit`` / ``shutdown`` contract and futures, but its threads are daemons: the
session still waits for them, bounded (:meth:`streamer.session.Session.close`), and names the
ones left; the interpreter does not. Loader threads only read and decode into memory, so
nothing is lost when a hung one is abandoned at exit.
"""

from __future__ import annotations

import queue
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

_STOP = None  # the sentinel a worker thread ends on


class DaemonPool:
    """Up to ``workers`` daemon threads named ``{prefix}_N``, started as work arrives.

    As in ``ThreadPoolExecutor``, the threads hold no reference to the pool: a pool nobody
    shut down (a session never closed) ends its idle threads when it is garbage-collected."""

    def __init__(self, workers: int, prefix: str) -> None:
        if workers < 1:
            raise ValueError(f"a pool needs at least one worker, got workers={workers}")
        self._workers = workers
        self._prefix = prefix
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._idle = threading.Semaphore(0)
        self._threads: list[threading.Thread] = []
        self._shutdown = False
        weakref.finalize(self, _stop, self._queue, workers)

    @property
    def threads(self) -> list[threading.Thread]:
        """The worker threads started so far (alive or not)."""
        with self._lock:
            return list(self._threads)

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future:
        """Run ``fn(*args)`` on a worker thread; its future. ``RuntimeError`` after shutdown."""
        with self._lock:
            if self._shutdown:
                raise RuntimeError("cannot schedule new work after the pool shut down")
            fut: Future = Future()
            self._queue.put((fut, fn, args))
            if not self._idle.acquire(blocking=False) and len(self._threads) < self._workers:
                t = threading.Thread(
                    target=_work,
                    args=(self._queue, self._idle),
                    name=f"{self._prefix}_{len(self._threads)}",
                    daemon=True,
                )
                t.start()
                self._threads.append(t)
            return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Take no more work; with ``cancel_futures`` cancel what has not started; with
        ``wait`` join the threads (unbounded: callers that may meet a hung read pass False
        and join :attr:`threads` with their own deadline)."""
        dropped = []
        with self._lock:
            self._shutdown = True
            if cancel_futures:
                while True:
                    try:
                        item = self._queue.get_nowait()
                    except queue.Empty:
                        break
                    if item is not _STOP:
                        dropped.append(item[0])
            for _ in self._threads:
                self._queue.put(_STOP)
            threads = list(self._threads)
        for fut in dropped:  # outside the lock: a done callback may call submit (and be refused)
            fut.cancel()
        if wait:
            for t in threads:
                t.join()


def _stop(q: queue.SimpleQueue, n: int) -> None:
    """End up to ``n`` workers of a collected pool (once each has finished its work)."""
    for _ in range(n):
        q.put(_STOP)


def _work(q: queue.SimpleQueue, idle: threading.Semaphore) -> None:
    """A worker thread's loop: run items until the stop sentinel (no reference to the pool)."""
    while True:
        item = q.get()
        if item is _STOP:
            return
        fut, fn, args = item
        del item
        if fut.set_running_or_notify_cancel():
            try:
                result = fn(*args)
            except BaseException as exc:  # as ThreadPoolExecutor: the future carries it
                fut.set_exception(exc)
                del exc
            else:
                fut.set_result(result)
                del result
        del fut, fn, args
        idle.release()
