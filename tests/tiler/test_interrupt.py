"""tiler.interrupt: Ctrl-C during a block run is raised between waits, never inside a lock.

The positive control reproduces the hang of a pool interrupted the old way: a SIGINT arriving
as ``threading.Condition.__enter__`` returns (the future's lock taken, the ``with`` body not yet
entered) leaves the lock held, and the pool's shutdown then never finishes.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures

import pytest

from tiler.interrupt import DeferredInterrupt, wait_first


def _sigint_when_condition_entered() -> None:
    """Deliver SIGINT (in this thread) as the next ``Condition.__enter__`` returns."""
    code = threading.Condition.__enter__.__code__

    def local(frame, event, arg):
        if event == "return":
            sys.settrace(None)
            signal.raise_signal(signal.SIGINT)
        return local

    def tracer(frame, event, arg):
        return local if event == "call" and frame.f_code is code else None

    sys.settrace(tracer)


def _shutdown_finishes(pool: ThreadPoolExecutor, timeout: float) -> bool:
    t = threading.Thread(target=pool.shutdown, name="test-shutdown", daemon=True)
    t.start()
    t.join(timeout)
    return not t.is_alive()


def _blocked_pool() -> tuple[ThreadPoolExecutor, threading.Event, object]:
    release = threading.Event()
    pool = ThreadPoolExecutor(1, thread_name_prefix="test-interrupt")
    return pool, release, pool.submit(release.wait, 30)


def test_positive_control_a_raised_interrupt_leaves_the_future_locked_and_shutdown_hangs():
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    pool, release, fut = _blocked_pool()
    try:
        _sigint_when_condition_entered()
        with pytest.raises(KeyboardInterrupt):
            fut.done()  # `with self._condition:` in the main thread
        release.set()  # the worker finishes and must take fut's lock to set the result ...
        assert not _shutdown_finishes(pool, 1.0)  # ... which this thread still holds: hang
    finally:
        sys.settrace(None)
        fut._condition.release()  # the leaked lock (owned by this thread)
    assert _shutdown_finishes(pool, 10.0)


def test_deferred_interrupt_only_flags_and_shutdown_finishes():
    pool, release, fut = _blocked_pool()
    with DeferredInterrupt() as interrupt:
        assert interrupt.installed
        try:
            _sigint_when_condition_entered()
            assert fut.done() is False  # returned normally: the lock was released
        finally:
            sys.settrace(None)
        assert interrupt.interrupted
        with pytest.raises(KeyboardInterrupt):
            interrupt.check()
        release.set()
        assert _shutdown_finishes(pool, 10.0)
        interrupt.interrupted = False
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def _interrupted_inside(error: BaseException | None) -> DeferredInterrupt:
    with DeferredInterrupt() as interrupt:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs here: no exception
        assert interrupt.interrupted
        if error is not None:
            raise error
    return interrupt


def test_an_interrupt_after_the_last_check_is_raised_on_leaving():
    with pytest.raises(KeyboardInterrupt):
        _interrupted_inside(None)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_raise_on_exit_false_keeps_the_flag_and_raises_nothing():
    with DeferredInterrupt(raise_on_exit=False) as interrupt:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
    assert interrupt.interrupted
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_error_leaving_the_block_is_not_replaced_by_the_interrupt():
    with pytest.raises(ValueError, match="the run's own error"):
        _interrupted_inside(ValueError("the run's own error"))


def test_a_callers_handler_and_other_threads_are_left_alone():
    seen = []
    old = signal.signal(signal.SIGINT, lambda *a: seen.append(1))
    try:
        with DeferredInterrupt() as interrupt:
            assert not interrupt.installed
            signal.raise_signal(signal.SIGINT)
        assert seen == [1] and not interrupt.interrupted
    finally:
        signal.signal(signal.SIGINT, old)
    box = []

    def other():
        with DeferredInterrupt() as d:
            box.append(d.installed)

    t = threading.Thread(target=other, name="test-other")
    t.start()
    t.join(10)
    assert box == [False]


def _wait(fs, timeout):
    return wait_futures(fs, timeout=timeout, return_when=FIRST_COMPLETED).done


def test_wait_first_returns_the_finished_and_times_out_empty():
    with ThreadPoolExecutor(2, thread_name_prefix="test-wait") as pool:
        gate = threading.Event()
        slow, quick = pool.submit(gate.wait, 30), pool.submit(lambda: 1)
        with DeferredInterrupt() as interrupt:
            assert wait_first(_wait, {slow, quick}, 10.0, interrupt, poll_s=0.05) == {quick}
            t0 = time.monotonic()
            assert wait_first(_wait, {slow}, 0.3, interrupt, poll_s=0.05) == set()
            assert 0.25 < time.monotonic() - t0 < 5
        gate.set()


def test_wait_first_raises_a_ctrl_c_within_a_poll():
    with ThreadPoolExecutor(1, thread_name_prefix="test-wait") as pool:
        gate = threading.Event()
        slow = pool.submit(gate.wait, 30)
        timer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT))
        try:
            with DeferredInterrupt() as interrupt:
                timer.start()
                t0 = time.monotonic()
                with pytest.raises(KeyboardInterrupt):
                    wait_first(_wait, {slow}, 30.0, interrupt, poll_s=0.05)
                assert time.monotonic() - t0 < 5  # not the 30 s timeout
                interrupt.interrupted = False
        finally:
            timer.cancel()
            gate.set()
