"""``render.builds.BackgroundBuilds``: one named worker, the latest build per key, errors
raised on the caller's thread, bounded waits, a clean stop (no GL)."""

from __future__ import annotations

import threading
import time

import pytest

from render.builds import THREAD_PREFIX, BackgroundBuilds, BuildError


def _workers() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX)]


def _done(builds: BackgroundBuilds, timeout: float = 10.0) -> list:
    builds.wait(timeout)
    return builds.done()


def test_a_build_runs_on_the_named_worker_and_is_handed_back_once():
    b = BackgroundBuilds()
    try:
        assert b.want("blk", 7, lambda: threading.current_thread().name)
        assert not b.want("blk", 7, lambda: "again")  # already pending
        [(key, version, name)] = _done(b)
        assert (key, version) == ("blk", 7) and name.startswith(THREAD_PREFIX)
        assert b.done() == [] and len(b) == 0
    finally:
        b.close()
    assert _workers() == []


def test_only_the_latest_version_of_a_key_is_handed_back():
    gate = threading.Event()
    b = BackgroundBuilds()
    try:
        b.want("blk", 5, lambda: gate.wait(10) and "five")  # running, held at the gate
        b.want("blk", 6, lambda: "six")  # replaces it
        b.want("other", 1, lambda: "one")
        assert b.pending("blk") == 6
        gate.set()
        got = sorted(_done(b))
        assert got == [("blk", 6, "six"), ("other", 1, "one")]
    finally:
        gate.set()
        b.close()


def test_control_a_key_asked_once_per_version_is_built_per_version():
    b = BackgroundBuilds()
    try:
        b.want("blk", 5, lambda: "five")
        assert _done(b) == [("blk", 5, "five")]
        b.want("blk", 6, lambda: "six")
        assert _done(b) == [("blk", 6, "six")]
    finally:
        b.close()


def test_a_failed_build_is_raised_where_results_are_taken():
    b = BackgroundBuilds("a test texture")

    def fail():
        raise ValueError("bad grid")

    try:
        b.want((3, 4), 9, fail)
        with pytest.raises(BuildError, match=r"a test texture for \(3, 4\).*bad grid") as e:
            _done(b)
        assert isinstance(e.value.__cause__, ValueError)
    finally:
        b.close()


def test_the_builds_finished_beside_a_failed_one_are_not_lost():
    b = BackgroundBuilds()

    def fail():
        raise OSError("disk gone")

    try:
        b.want("ok", 1, lambda: "built")
        b.want("bad", 1, fail, "loading the kernels")
        with pytest.raises(BuildError, match="^loading the kernels failed: disk gone"):
            _done(b)
        assert b.done() == [("ok", 1, "built")]
    finally:
        b.close()


def test_waits_are_bounded():
    gate = threading.Event()
    b = BackgroundBuilds()
    try:
        b.want("slow", 1, lambda: gate.wait(10))
        t0 = time.monotonic()
        with pytest.raises(BuildError, match="still running after 0.2 s"):
            b.wait(0.2)
        with pytest.raises(BuildError, match="still ran 0.2 s after close"):
            b.close(timeout=0.2)
        assert time.monotonic() - t0 < 5.0
    finally:
        gate.set()
    deadline = time.monotonic() + 10.0
    while _workers() and time.monotonic() < deadline:  # it ends after its build
        time.sleep(0.01)
    assert _workers() == []


def test_close_waits_for_a_replaced_build_still_running_bounded():
    gate = threading.Event()
    b = BackgroundBuilds()
    try:
        b.want("blk", 1, lambda: gate.wait(10))  # running, then replaced
        time.sleep(0.05)
        b.want("blk", 2, lambda: "two")
        t0 = time.monotonic()
        with pytest.raises(BuildError, match="still ran 0.2 s after close"):
            b.close(timeout=0.2)
        assert time.monotonic() - t0 < 5.0
    finally:
        gate.set()


def test_close_cancels_what_has_not_started():
    gate = threading.Event()
    ran: list[str] = []
    b = BackgroundBuilds()
    b.want("first", 1, lambda: gate.wait(10))
    b.want("second", 1, lambda: ran.append("second"))
    threading.Timer(0.1, gate.set).start()
    b.close()
    assert ran == [] and _workers() == []
