"""A server that fails slowly (every read times out after a while) must not hold a session's
waits to their deadlines: the warm-up ends once every block it waits for has failed its
retries, and ``update(wait=True)`` fails naming a block, because failed blocks take turns
instead of the most urgent few keeping every worker. Without workers (``render``, ``tradeoff``:
loads on the caller's thread) a read slower than its retry's backoff kept the caller retrying
the most urgent block for ever, past any deadline. Each fix has its control: the code before
it, patched back in, runs into the deadline (or past it) with visible blocks never read."""

from __future__ import annotations

import collections
import heapq
import threading
import time

import pytest
from demtools import fractal, write_dem

import streamer.waits
from streamer.errors import LoadError
from streamer.loader import Loader
from streamer.loadqueue import LoadQueue
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile

READ_S = 0.02  # each read fails after this long (a timeout, scaled down)
DEADLINE_S = 4.0
#: backoff capped well below a round of retries (80 blocks x READ_S / 2 workers): the
#: failed blocks alone could keep both workers busy, as a real timeout (1-10 s) does
#: no raise at the first failed block: the wait then waits for every visible block
OPTIONS = dict(budget_mb=64, workers=2, backoff_s=0.005, max_backoff_s=0.02,
               wait_timeout_s=DEADLINE_S, raise_on_failure=False)  # fmt: skip


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
        try:
            out["failed"] = len(s.update(cam, wait=True).failed)
        except LoadError as exc:
            out["wait_error"] = str(exc)
        out["wait_s"] = time.monotonic() - t
        out["unread"] = sorted(b for b in visible if hook.reads[b] == 0)
        out["visible"] = len(visible)
        s.close()
    return out


def test_a_slowly_failing_server_ends_the_waits_long_before_their_deadlines(store):
    out = fly(store)
    assert out["visible"] > 10, "the camera must see many blocks for the test to mean anything"
    assert "warm_error" not in out and out["warm_s"] < DEADLINE_S, out
    # the waiting frame tried every visible block, and ended when each had failed its retries
    assert out["unread"] == [] and out["wait_s"] < DEADLINE_S, out
    assert "wait_error" not in out and out["failed"] == out["visible"], out


def _no_pause(monkeypatch) -> None:
    """The waits as before their pause: blocks that gave up are retried during the wait."""
    import contextlib

    import streamer.session

    def retrying(ld, since):
        return contextlib.nullcontext()

    monkeypatch.setattr(streamer.waits, "waiting", retrying)
    monkeypatch.setattr(streamer.session, "waiting", retrying)


def test_positive_control_without_the_given_up_check_the_warm_up_runs_to_its_deadline(
    store, monkeypatch
):
    monkeypatch.setattr(streamer.waits, "only_given_up", lambda ld, since: False)
    _no_pause(monkeypatch)  # (else the paused retries let the loader go idle: the wait ends)
    out = fly(store)
    assert out["warm_s"] >= DEADLINE_S, out
    assert "warm-up did not finish within 4.0 s" in out["warm_error"]


def _warm_up_reads(store) -> collections.Counter:
    """Reads per block during a warm-up over a server that fails every read slowly."""
    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    hook = SlowFailures()
    with open_session(store, **OPTIONS) as s:
        s._read_hook = hook
        s.warm_up(cam)
        with hook.lock:
            reads = collections.Counter(hook.reads)
        s.close()
    return reads


def test_a_warm_up_over_a_failing_server_reads_each_block_retries_times(store):
    """Once a block has failed its retries since the warm-up began, it is not retried until
    the warm-up ends: each block is read exactly ``retries`` times (a worker retrying blocks
    that gave up read some 11 times, and the warm-up took ~1.6x as long)."""
    reads = _warm_up_reads(store)
    assert len(reads) > 10 and set(reads.values()) == {3}, reads


def test_positive_control_without_the_pause_blocks_that_gave_up_are_read_again(store, monkeypatch):
    _no_pause(monkeypatch)
    reads = _warm_up_reads(store)
    assert max(reads.values()) > 3 + 1, reads


def key_order_pop(self, now, take, probe=True):
    """The queue before failed blocks waited apart: one heap, in key order (and no sleeping
    heap: blocks in backoff stay in it)."""
    self._wake(float("inf"))
    self._heap.extend((entry[-1], b) for entry, b in self._failed)
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


# -- without workers: loads on the caller's thread ------------------------------------------


class Stop(BaseException):
    """Ends a control's endless loop from inside its read hook."""


def inline_wait(store, stop: threading.Event) -> dict:
    """``update(wait=True)`` on a session without workers whose reads all fail slowly (slower
    than the capped backoff), in a thread: what it raised and when, or that it never ended."""
    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    hook = SlowFailures()

    def read(block, level):
        if stop.is_set():
            raise Stop
        hook(block, level)

    out: dict = {}
    s = open_session(store, budget_mb=64, workers=0, backoff_s=0.001, max_backoff_s=0.01,
                     wait_timeout_s=DEADLINE_S)  # fmt: skip
    s._read_hook = read

    def run():
        t = time.monotonic()
        try:
            s.update(cam, wait=True)
        except LoadError as exc:
            out["error"] = str(exc)
        except Stop:
            out["stopped"] = True
        out["s"] = time.monotonic() - t

    th = threading.Thread(target=run, name="test-inline-wait", daemon=True)
    th.start()
    th.join(timeout=2 * DEADLINE_S)
    out["alive"] = th.is_alive()
    stop.set()
    th.join(timeout=10)
    out["reads"] = dict(hook.reads)
    s.close()
    return out


def test_without_workers_a_slowly_failing_server_fails_the_frame_naming_a_block(store):
    out = inline_wait(store, threading.Event())
    assert not out["alive"] and out["s"] < DEADLINE_S, out
    assert "could not be read after 3 tries" in out["error"], out
    # breadth first: every block was read before one failed its last retry
    assert len(out["reads"]) > 10 and max(out["reads"].values()) == 3, out["reads"]


def old_load_inline(self, allowance, deadline=None):
    """``load_inline`` before one pass per call: jobs until none can be taken now."""
    spent = 0
    while allowance is None or spent < allowance:
        with self.cv:
            job = None if self.fatal is not None else self.next_job()
        if job is None:
            return False
        before = self.totals.loaded_bytes
        self.run_job(job)
        spent += self.totals.loaded_bytes - before
    return True


def test_positive_control_retrying_until_nothing_is_due_never_ends(store, monkeypatch):
    monkeypatch.setattr(Loader, "load_inline", old_load_inline)
    out = inline_wait(store, threading.Event())
    assert out["alive"], out  # still retrying at twice its deadline
    assert out.get("stopped"), out  # ended only by the hook
    # the same few most urgent blocks retried all along, the others never read
    assert len(out["reads"]) <= 3 and sum(out["reads"].values()) > 50, out["reads"]
