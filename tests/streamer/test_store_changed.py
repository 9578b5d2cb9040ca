"""A store replaced under a reader or a session: the change is final. Once a reader has seen
it, every later read raises :class:`StoreChangedError` (no more chunks of the new store are
mixed with the old one's), and a session stops loading and raises it on every later call,
instead of retrying it as a block's read failure. Also: ``close()`` from another thread ends an
``update(wait=True)`` in progress."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

import tiler.store as store_mod
from streamer.errors import SessionClosedError
from streamer.paths import default_flythrough
from streamer.run import flight_problem
from streamer.session import open_session
from tiler.errors import StoreChangedError
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile


def _tile(tmp, name, seed):
    src = write_dem(tmp / f"{name}.tif", fractal((257, 321), seed), cell=10.0)
    tile(src, tmp / f"{name}.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


@pytest.fixture
def root(tmp_path):
    """``s.zarr`` (served) and ``b.zarr`` (same shape, other heights) to put in its place."""
    _tile(tmp_path, "s", 5)
    _tile(tmp_path, "b", 6)
    return tmp_path


def _replace(root):
    os.rename(root / "s.zarr", root / "old.zarr")
    os.rename(root / "b.zarr", root / "s.zarr")


def _cameras(store, n=30):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, viewport=(160, 120))


def test_a_remote_reader_that_saw_the_change_never_reads_the_new_store(root, monkeypatch):
    """The change is seen at most once a second on a remote store; once seen, every read
    raises it, even inside that second. The control: before the latch, a read inside the
    second after a change returns the new store's heights (the window documented)."""
    with LoopbackServer(root) as url:
        st = TerrainStore(f"{url}/s.zarr")
        old = st.read_block((1, 1))
        monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 1e9)
        _replace(root)
        new = st.read_block((1, 1))  # inside the interval: not checked yet
        assert not np.array_equal(new, old)  # the window: the new store's heights
        with pytest.raises(StoreChangedError, match="replaced or rewritten"):
            st.check_unchanged(force=True)
        for _ in range(3):  # still inside the interval: the change is remembered
            with pytest.raises(StoreChangedError, match="replaced or rewritten"):
                st.read_block((1, 1))
        with pytest.raises(StoreChangedError):
            st.read_mask((0, 0))


def test_a_local_reader_stays_failed_after_the_change(root):
    st = TerrainStore(root / "s.zarr")
    st.read_block((0, 0))
    _replace(root)
    for _ in range(2):
        with pytest.raises(StoreChangedError):
            st.read_level_raw((0, 0), 0)


def _fly(url, root, *, replace_at):
    """A 30-frame flight over the served store, replaced before frame ``replace_at`` (None:
    never); returns (frames flown, the error raised or None, reads started after it, summary)."""
    st = TerrainStore(f"{url}/s.zarr")
    reads = []
    with open_session(st, budget_mb=64, workers=2, raise_on_failure=True) as s:
        s._read_hook = lambda b, lv: reads.append(time.monotonic())
        err, flown = None, 0
        for i, cam in enumerate(_cameras(st)):
            if i == replace_at:
                _replace(root)
                s.set_tau(0.25)  # finer levels: more reads after the change
            try:
                s.update(cam, wait=True)
            except StoreChangedError as exc:
                err = exc
                break
            flown += 1
        after = None
        if err is not None:
            seen = len(reads)
            for cam in _cameras(st)[flown:]:  # every later call raises it again
                with pytest.raises(StoreChangedError):
                    s.update(cam, wait=True)
            time.sleep(0.3)
            after = len(reads) - seen
        summary = s.summary()
        s.close()  # already raised: close does not raise it again
    return flown, err, after, summary


def test_a_session_stops_at_a_replaced_store_and_says_so(root, monkeypatch):
    monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 0.0)  # seen at its first read
    with LoopbackServer(root) as url:
        flown, err, after, summary = _fly(url, root, replace_at=5)
    assert flown == 5 and err is not None
    assert "the session stopped loading when it saw the change" in str(err)
    assert after == 0  # no read started after the change was seen
    # the reads in flight, and any that raced the swap (two renames: the store is briefly
    # absent, a 404), not a retry loop (the old code counted hundreds)
    assert summary["io_errors"] <= 6, summary["io_errors"]
    assert summary["store_changed"] and "replaced or rewritten" in summary["store_changed"]
    problem = flight_problem(summary, [], url)
    assert problem.startswith("the store was replaced or rewritten while it was streamed")


def test_the_same_flight_without_a_change_flies_on(root, monkeypatch):
    """The control: the same flight over an unchanged store flies every frame."""
    monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 0.0)
    with LoopbackServer(root) as url:
        flown, err, _, summary = _fly(url, root, replace_at=None)
    assert flown == 30 and err is None
    assert summary["store_changed"] is None and flight_problem(summary, [], url) is None


def test_close_from_another_thread_ends_a_waiting_update(root):
    """``update(wait=True)`` waiting on a stalled server ends with SessionClosedError when
    another thread closes the session, not after ``wait_timeout_s``."""
    srv = LoopbackServer(root)
    with srv as url:
        st = TerrainStore(f"{url}/s.zarr")
        s = open_session(st, budget_mb=64, workers=2, wait_timeout_s=20.0)
        srv.stall.set()
        out: dict = {}

        def waiter():
            t0 = time.monotonic()
            try:
                s.update(_cameras(st, 1)[0], wait=True)
            except Exception as exc:  # noqa: BLE001 - the test reads it
                out["exc"] = exc
            out["s"] = time.monotonic() - t0

        t = threading.Thread(target=waiter, name="test-waiter")
        t.start()
        time.sleep(0.5)
        assert t.is_alive()  # it waits for the stalled reads
        s.close(0.2)
        t.join(timeout=5)
        srv.release.set()
        assert not t.is_alive()
        assert isinstance(out.get("exc"), SessionClosedError), out
        assert out["s"] < 3.0
