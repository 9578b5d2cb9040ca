"""``streamer.pool.DaemonPool``: ThreadPoolExecutor's contract on named daemon threads."""

from __future__ import annotations

import threading

import pytest

from streamer.pool import DaemonPool


def test_results_exceptions_and_named_daemon_threads():
    pool = DaemonPool(2, "t-pool")
    try:
        assert pool.submit(lambda a, b: a + b, 2, 3).result(timeout=5) == 5
        err = pool.submit(lambda: 1 / 0).exception(timeout=5)
        assert isinstance(err, ZeroDivisionError)
        names = {pool.submit(lambda: threading.current_thread().name).result(timeout=5)
                 for _ in range(20)}  # fmt: skip
        assert names <= {"t-pool_0", "t-pool_1"}
        assert all(t.daemon for t in pool.threads)
        assert 1 <= len(pool.threads) <= 2
    finally:
        pool.shutdown(wait=True)
    assert not any(t.is_alive() for t in pool.threads)


def test_never_more_threads_than_workers_and_idle_ones_are_reused():
    pool = DaemonPool(3, "t-cap")
    gate = threading.Event()
    try:
        futs = [pool.submit(gate.wait, 5) for _ in range(10)]
        assert len(pool.threads) == 3  # seven wait in the queue
        gate.set()
        assert all(f.result(timeout=5) for f in futs)
        for _ in range(10):  # sequential work after that starts no thread
            pool.submit(int).result(timeout=5)
        assert len(pool.threads) == 3
    finally:
        gate.set()
        pool.shutdown(wait=True)


def test_shutdown_cancels_queued_work_and_refuses_new():
    pool = DaemonPool(1, "t-cancel")
    gate = threading.Event()
    running = pool.submit(gate.wait, 5)
    queued = [pool.submit(int) for _ in range(3)]
    done: list[bool] = []
    queued[0].add_done_callback(lambda f: done.append(f.cancelled()))
    pool.shutdown(wait=False, cancel_futures=True)
    assert all(f.cancelled() for f in queued) and done == [True]
    assert not running.cancelled()  # started work runs to its end
    with pytest.raises(RuntimeError, match="shut down"):
        pool.submit(int)
    gate.set()
    assert running.result(timeout=5) is True
    for t in pool.threads:
        t.join(timeout=5)
        assert not t.is_alive()


def test_control_without_cancel_queued_work_still_runs():
    pool = DaemonPool(1, "t-drain")
    futs = [pool.submit(lambda i=i: i) for i in range(5)]
    pool.shutdown(wait=True)
    assert [f.result(timeout=0) for f in futs] == list(range(5))


def test_a_pool_needs_a_worker():
    with pytest.raises(ValueError, match="workers=0"):
        DaemonPool(0, "t-none")


def _alive(prefix: str) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(prefix)]


def _wait_gone(prefix: str, timeout_s: float = 5.0) -> list[str]:
    import time

    deadline = time.monotonic() + timeout_s
    while _alive(prefix) and time.monotonic() < deadline:
        time.sleep(0.01)
    return _alive(prefix)


def test_a_pool_never_shut_down_ends_its_idle_threads_when_collected():
    """A session nobody closed must not leak its loader threads (ThreadPoolExecutor's
    behaviour too): the threads hold no reference to the pool."""
    import gc

    pool = DaemonPool(2, "t-gc")
    assert pool.submit(int, "7").result(timeout=5) == 7
    assert _alive("t-gc")
    del pool
    gc.collect()
    assert _wait_gone("t-gc") == []


def test_control_a_live_pool_keeps_its_idle_threads():
    import time

    pool = DaemonPool(2, "t-live")
    pool.submit(int).result(timeout=5)
    time.sleep(0.2)
    assert _alive("t-live")  # idle, waiting for work: not ended while the pool lives
    pool.shutdown(wait=True)
    assert _alive("t-live") == []


def test_a_cancelled_futures_callback_may_submit_and_is_refused_not_deadlocked():
    """Done callbacks of the futures ``shutdown`` cancels run in the caller's thread; one that
    submits again (a loader pumping its queue) is refused, not blocked on the pool's lock."""
    pool = DaemonPool(1, "t-cb")
    gate = threading.Event()
    pool.submit(gate.wait, 5)
    refused: list[str] = []

    def resubmit(_fut):
        try:
            pool.submit(int)
        except RuntimeError as exc:
            refused.append(str(exc))

    pool.submit(int).add_done_callback(resubmit)
    done = threading.Event()
    t = threading.Thread(
        target=lambda: (pool.shutdown(wait=False, cancel_futures=True), done.set()),
        daemon=True,
    )
    t.start()
    assert done.wait(5), "shutdown deadlocked in a cancelled future's callback"
    assert refused and "shut down" in refused[0]
    gate.set()
    pool.shutdown(wait=True)
