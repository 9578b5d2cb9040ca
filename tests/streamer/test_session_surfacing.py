"""What a session says when reads go wrong: loader bugs surface with their cause (not as a
timeout, not retried while a wait runs out, not dropped by close), failing blocks are told
apart by whether a frame needed them and by cause, a server that stops answering leaves its
reads visible at close, and the verdict ``stream`` exits with
(:func:`streamer.run.flight_problem`)."""

from __future__ import annotations

import logging
import threading
import time

import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

from streamer.errors import LodError, SessionClosedError
from streamer.paths import default_flythrough
from streamer.run import CLOSE_WAIT_S, flight_problem
from streamer.session import open_session
from tiler.location import Location
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("surfacing")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 5), cell=10.0)
    tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))
    return tmp


@pytest.fixture(scope="module")
def store(root):
    return TerrainStore(root / "s.zarr")


def camera(store):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]


class Bug:
    """A read hook with a bug: raises ``ZeroDivisionError`` on every read; counts its calls."""

    def __init__(self) -> None:
        self.calls = 0
        self.lock = threading.Lock()

    def __call__(self, block, level) -> None:
        with self.lock:
            self.calls += 1
        raise ZeroDivisionError("the hook's bug")


# -- loader bugs -----------------------------------------------------------------------------


def test_a_loader_bug_ends_a_wait_with_its_cause_not_a_timeout(store):
    bug = Bug()
    with open_session(store, budget_mb=8, workers=2, wait_timeout_s=30.0) as s:
        s._read_hook = bug
        t0 = time.monotonic()
        with pytest.raises(ZeroDivisionError, match="the hook's bug") as e:
            s.update(camera(store), wait=True)
        assert time.monotonic() - t0 < 5.0  # was: the whole wait, then an opaque LoadError
        assert any("loader thread reading" in n for n in e.value.__notes__)
        time.sleep(0.3)
        # no job starts while a bug waits to be raised: the failing reads are not retried
        assert bug.calls <= 2 * s.config.workers, bug.calls
        s._read_hook = None  # the bug fixed: the session goes on
        for _ in range(s.config.workers + 1):
            try:
                f = s.update(camera(store), wait=True)
                break
            except ZeroDivisionError:  # a read that hit the bug before the fix, reported once
                continue
        else:
            pytest.fail("the session kept raising after the bug was gone")
        assert not f.stats.stalled


def test_warm_up_raises_a_loader_bug(store):
    with open_session(store, budget_mb=8, workers=2, wait_timeout_s=30.0) as s:
        s._read_hook = Bug()
        t0 = time.monotonic()
        with pytest.raises(ZeroDivisionError):
            s.warm_up(camera(store))
        assert time.monotonic() - t0 < 5.0


def test_close_raises_a_bug_no_update_reported(store):
    s = open_session(store, budget_mb=8, workers=1)
    s._read_hook = Bug()
    s.update(camera(store))  # queues the view's loads; the first read hits the bug later
    deadline = time.monotonic() + 5
    while s.loader.bug is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert s.loader.bug is not None
    with pytest.raises(ZeroDivisionError):  # was: dropped
        s.close()
    assert s.close() == []  # closed once; a second close is a no-op


def test_exiting_with_an_exception_keeps_it_and_logs_the_bug(store, caplog):
    caplog.set_level(logging.ERROR, logger="streamer.session")

    def fly() -> None:
        with open_session(store, budget_mb=8, workers=1) as s:
            s.loader.bug = ZeroDivisionError("pending")  # a bug no update re-raised yet
            raise RuntimeError("the caller's own")

    with pytest.raises(RuntimeError, match="the caller's own"):
        fly()
    assert "pending" in caplog.text


def test_set_tau_checks_the_session_and_the_value(store):
    s = open_session(store, budget_mb=8, workers=0)
    for bad in (None, "2", True):
        with pytest.raises(LodError, match="tau must be a number"):
            s.set_tau(bad)
    s.set_tau(2)
    assert s.config.tau == 2.0
    s.close()
    with pytest.raises(SessionClosedError):
        s.set_tau(1.0)


# -- failing blocks: needed or read ahead, server or store -------------------------------------


def _ahead_only(store) -> tuple:
    """A block the session reads ahead of a still camera but no frame of it needs."""
    cam = camera(store)
    with open_session(store, budget_mb=64, workers=2) as s:
        s.warm_up(cam)
        visible = set(s.planner.needed(cam))
        ahead = sorted({b for b, _ in s.loader.ever_loaded} - visible)
    assert ahead, "the still camera reads nothing ahead: no block to fail"
    return ahead[0]


def _fly_still(store, hook_block, frames=30):
    def hook(block, level):
        if block == hook_block:
            raise OSError("injected read failure")

    cam = camera(store)
    with open_session(
        store, budget_mb=64, workers=2, retries=2, backoff_s=0.001, raise_on_failure=False
    ) as s:
        s._read_hook = hook
        s.warm_up(cam)
        for i in range(frames):
            s.update(cam, wait=(i == 0))
            time.sleep(0.01)
        s.close()
        return s.summary()


def test_a_block_only_read_ahead_fails_without_a_frame_needing_it(store):
    b = _ahead_only(store)
    end = _fly_still(store, b)
    assert end["failed_blocks"] == [list(b)] and end["failing_blocks"] == 1
    assert end["failing_blocks_needed"] == 0 and end["failed_blocks_ever"] == 0
    assert end["stall_frames"] == 0
    problem = flight_problem(end, [], "s.zarr")
    assert problem.startswith("1 block(s) read ahead of the camera failed every retry")
    assert "no frame needed them" in problem and "terrastream verify s.zarr" in problem
    # the control: the same failure on a block the frames need is named as such
    with open_session(store, workers=0) as s0:
        visible = next(iter(s0.planner.needed(camera(store))))
    end = _fly_still(store, visible)
    assert end["failing_blocks_needed"] == 1 and end["failed_blocks_ever"] == 1
    assert flight_problem(end, [], "s.zarr").startswith("1 block(s) a frame needed could not")


# -- a server that stops answering ----------------------------------------------------------


def _fly_into_a_stall(srv, store, **kw):
    """A session over ``store`` whose server answers no block read: a few frames that queue
    reads (none waits); returns the open session."""
    s = open_session(store, budget_mb=64, workers=2, **kw)
    srv.stall.set()  # the store's metadata and index were read when it was opened
    cams = default_flythrough(
        s.grid, *s.store.meta.extra["value_range"], 20, 60.0, viewport=(160, 120)
    )
    for cam in cams:
        s.update(cam)
        time.sleep(0.02)
    return s


def test_reads_a_stalled_server_never_answers_are_left_visible_at_close(root):
    srv = LoopbackServer(root)
    with srv as url:
        s = _fly_into_a_stall(srv, TerrainStore(f"{url}/s.zarr"))
        unfinished = s.close(0.5)  # the default timeout (30 s) has not run out
        assert [n for n in unfinished if n.startswith("terrastream-load")]
        # the planning thread does no I/O: it has ended while the reads were awaited
        assert not [n for n in unfinished if n.startswith("terrastream-plan")], unfinished
        assert s.summary()["io_errors"] == 0  # nothing failed yet: the reads just hang
        problem = flight_problem(s.summary(), unfinished, url)
        assert "still unanswered" in problem and "stopped answering" in problem
        srv.release.set()  # the hung reads fail now: their threads end inside the test
        for t in threading.enumerate():
            if t.name.startswith("terrastream-load"):
                t.join(timeout=10)
        assert not [t for t in threading.enumerate() if t.name.startswith("terrastream-load")]


def test_with_a_timeout_a_stalled_server_becomes_failed_reads_of_the_server(root):
    srv = LoopbackServer(root)
    with srv as url:
        # not shorter: a loaded machine can take 0.3 s to connect on loopback (seen in CI)
        st = TerrainStore(Location(f"{url}/s.zarr", {"timeout": 1.0}))
        s = _fly_into_a_stall(srv, st, raise_on_failure=False)
        assert s.close(5.0) == []  # every read gave up within its timeout
        end = s.summary()
    assert end["io_errors"] >= 1 and end["failing_blocks"] >= 1
    assert end["failing_blocks_needed"] >= 1  # the frames' own blocks
    assert end["failing_blocks_unreachable"] == end["failing_blocks"]
    assert "did not answer in time" in end["last_read_error"]
    problem = flight_problem(end, [], url)
    assert problem and "the server or the network failed, not the store" in problem
    assert "verify" not in problem


# -- the verdict, pure -------------------------------------------------------------------------


def test_flight_problem_verdicts():
    ok = {"loaded_bytes": 10, "failing_blocks": 0, "failed_blocks": []}
    assert flight_problem(ok, [], "u") is None
    assert flight_problem(ok, ["terrastream-plan_0"], "u") is None  # planning, not a read
    hung = flight_problem(ok, ["terrastream-load_1"], "u")
    assert hung.startswith(f"1 read(s) of 'u' were still unanswered {CLOSE_WAIT_S:.0f} s")
    assert "no level could be loaded" in flight_problem({**ok, "loaded_bytes": 0}, [], "u")
    # a read ahead that failed once and may still work is no failure
    once = {**ok, "failing_blocks": 1, "failing_blocks_needed": 0}
    assert flight_problem(once, [], "u") is None
    damaged = {
        **ok,
        "failing_blocks": 2,
        "failing_blocks_needed": 2,
        "failing_blocks_unreachable": 1,
        "failed_blocks": [[0, 0]],
        "last_read_error": "checksum",
    }
    text = flight_problem(damaged, [], "u")
    assert text.startswith("2 block(s) a frame needed could not be read by the end (1 failed")
    assert "terrastream verify u" in text and "latest error: checksum" in text
    server = {**damaged, "failing_blocks_unreachable": 2, "last_read_error": "503"}
    assert "the server or the network failed" in flight_problem(server, [], "u")


def test_a_replaced_store_is_not_called_damaged():
    """A store replaced mid-flight (``store_changed``, set from ``StoreChangedError``) says so,
    not "verify"; the control: a checksum error still sends the user to ``terrastream verify``."""
    base = {"loaded_bytes": 10, "failed_blocks": [(0, 0)], "failing_blocks": 1,
            "failing_blocks_needed": 1, "failing_blocks_unreachable": 0}  # fmt: skip
    changed = "store 'u' was replaced or rewritten while it was open (generation 'a' -> 'b')"
    problem = flight_problem({**base, "store_changed": changed}, [], "u")
    assert "replaced or rewritten while it was streamed" in problem and "verify" not in problem
    damaged = flight_problem({**base, "last_read_error": "crc32c checksum mismatch"}, [], "u")
    assert "terrastream verify u" in damaged
