"""A server that fails slowly (every read times out after a while) must not hold a session's
waits to their deadlines: the warm-up ends once every block it waits for has failed its
retries, and ``update(wait=True)`` fails naming a block, because failed blocks take turns
instead of the most urgent few keeping every worker. Each fix has its control: the code
before it, patched back in, runs into the deadline with visible blocks never read."""

from __future__ import annotations

import collections
import heapq
import threading
import time

import pytest
from demtools import fractal, write_dem

import streamer.waits
from streamer.errors import LoadError
from streamer.loadqueue import LoadQueue
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile

READ_S = 0.02  # each read fails after this long (a timeout, scaled down)
DEADLINE_S = 4.0
#: backoff capped well below a round of retries (80 blocks x READ_S / 2 workers): the
#: failed blocks alone could keep both workers busy, as a real timeout (1-10 s) does
OPTIONS = dict(budget_mb=64, workers=2, backoff_s=0.005, max_backoff_s=0.02,
               wait_timeout_s=DEADLINE_S)  # fmt: skip


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("slow")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


class SlowFailures:
    """A ``read_hook`` failing every read after ``READ_S``; counts reads per block."""

    def __init__(self) -> None:
        self.reads: collections.Counter = collections.Counter()
        self.lock = threading.Lock()

    def __call__(self, block, level) -> None:
        with self.lock:
            self.reads[block] += 1
        time.sleep(READ_S)
        raise OSError("injected slow failure")


def fly(store) -> dict:
    """Warm up for a camera, then one waiting frame; what each took and raised."""
    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    hook = SlowFailures()
    out: dict = {}
    with open_session(store, **OPTIONS) as s:
        s._read_hook = hook
        t = time.monotonic()
        try:
            s.warm_up(cam)
        except LoadError as exc:
            out["warm_error"] = str(exc)
        out["warm_s"] = time.monotonic() - t
        visible = set(s.planner.needed(cam))
        hook.reads.clear()
        t = time.monotonic()
        with pytest.raises(LoadError) as exc:
            s.update(cam, wait=True)
        out["wait_s"], out["wait_error"] = time.monotonic() - t, str(exc.value)
        out["unread"] = sorted(b for b in visible if hook.reads[b] == 0)
        out["visible"] = len(visible)
        s.close()
    return out


def test_a_slowly_failing_server_ends_the_waits_long_before_their_deadlines(store):
    out = fly(store)
    assert out["visible"] > 10, "the camera must see many blocks for the test to mean anything"
    assert "warm_error" not in out and out["warm_s"] < DEADLINE_S, out
    # the waiting frame tried every visible block and stopped on one that failed its retries
    assert out["unread"] == [] and out["wait_s"] < DEADLINE_S, out
    assert "could not be read after 3 tries" in out["wait_error"], out["wait_error"]


def test_positive_control_without_the_given_up_check_the_warm_up_runs_to_its_deadline(
    store, monkeypatch
):
    monkeypatch.setattr(streamer.waits, "only_given_up", lambda ld, since: False)
    out = fly(store)
    assert out["warm_s"] >= DEADLINE_S, out
    assert "warm-up did not finish within 4.0 s" in out["warm_error"]


def key_order_pop(self, now, take, probe=True):
    """The queue before failed blocks waited apart: one heap, in key order."""
    self._heap.extend((entry[1], b) for entry, b in self._failed)
    self._failed.clear()
    heapq.heapify(self._heap)
    waiting, found, best = [], None, self._best
    while self._heap:
        key, b = heapq.heappop(self._heap)
        if best.get(b) == key:
            del best[b]
        if not self.retryable(b):
            continue
        if self.backing_off(b, now):
            waiting.append((key, b))
            continue
        job = take(b)
        if job is not None:
            found = (b, job)
            break
    for key, b in waiting:
        heapq.heappush(self._heap, (key, b))
        if b not in best or key < best[b]:
            best[b] = key
    return found


def test_positive_control_in_key_order_the_wait_times_out_with_blocks_never_read(
    store, monkeypatch
):
    monkeypatch.setattr(LoadQueue, "pop", key_order_pop)
    out = fly(store)
    assert out["wait_s"] >= DEADLINE_S and "did not load within 4.0 s" in out["wait_error"]
    assert out["unread"], "every visible block was read: the control shows nothing"
