"""Sessions that heal: 10,000 frames with injected read faults (random failures, stalls, an
outage of every read). Asserts no hole after recovery but a block the injector failed 3 times
in a row since (reported failed), the budget never exceeded and no session threads left; the
positive control (retries disabled) shows the same faults do leave holes, which that check
flags. TERRASTREAM_RELIABILITY_LONG=1 runs a longer flight with full-length (500 ms) stalls."""

from __future__ import annotations

import os
import random
import threading
import time
from dataclasses import dataclass, field

import pytest
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import LoadError, open_session
from tiler.tile import TileOptions, tile

LONG = os.environ.get("TERRASTREAM_RELIABILITY_LONG") == "1"
FRAMES = 30_000 if LONG else 10_000
STALL_S = 0.5 if LONG else 0.05  # the fast run scales the 500 ms stalls down
OUTAGE_S = 0.5
BUDGET_MB = 0.05  # below what the flight visits: blocks are evicted and read again
AFTER_FRAMES = 1250  # frames flown after the outage has surely ended


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("faults")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


@dataclass
class Faults:
    """A ``read_hook``: fails ``p_fail`` of reads, stalls ``p_stall`` of them, and fails every
    read during an outage started by :meth:`start_outage`."""

    p_fail: float = 0.05
    p_stall: float = 0.01
    seed: int = 7
    outage: tuple[float, float] = (float("inf"), float("inf"))
    counts: dict = field(default_factory=lambda: {"fail": 0, "stall": 0, "outage": 0, "reads": 0})
    #: per block: injected failures in a row since the outage ended (reset by a read that is
    #: let through): a block the session may rightly report failed after recovery
    streak: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)
        self._lock = threading.Lock()

    def start_outage(self) -> None:
        now = time.monotonic()
        self.outage = (now, now + OUTAGE_S)

    def _failed(self, block, now: float) -> None:
        if now >= self.outage[1]:
            self.streak[block] = self.streak.get(block, 0) + 1

    def __call__(self, block, level) -> None:
        now = time.monotonic()
        with self._lock:
            self.counts["reads"] += 1
            u, v = self._rng.random(), self._rng.random()
            if self.outage[0] <= now < self.outage[1]:
                self.counts["outage"] += 1
                self._failed(block, now)
                raise ConnectionError(f"injected outage reading {block} level {level}")
            if u < self.p_fail:
                self.counts["fail"] += 1
                self._failed(block, now)
                raise OSError(f"injected failure reading {block} level {level}")
            self.streak[block] = 0
            stall = v < self.p_stall
            if stall:
                self.counts["stall"] += 1
        if stall:
            time.sleep(STALL_S)


def session_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("terrastream-")]


def recovery_s(session) -> float:
    """Time after the outage by which every block that failed in it has been retried: two
    capped backoffs when healing; at once without healing (nothing will be retried)."""
    return 2 * session.config.max_backoff_s if session.config.heal else 0.0


def fly(store, faults: Faults, frames: int = FRAMES, **options) -> dict:
    """Fly ``frames`` unpaced frames, waiting every 50th, with an outage a third of the way;
    return the waited frames' holes and failed blocks, budget overruns and the summary."""
    z0, z1 = store.meta.extra["value_range"]
    cams = default_flythrough(store.grid, z0, z1, frames, 60.0, viewport=(160, 120))
    budget = BUDGET_MB * 2**20
    out = {"waited": [], "over_budget": 0, "outage_frame": frames // 3}
    assert frames - AFTER_FRAMES > out["outage_frame"], "the flight is too short to end after"
    with open_session(
        store, budget_mb=BUDGET_MB, workers=3, tau=2.0, raise_on_failure=False, **options
    ) as s:
        s._read_hook = faults
        recovered_at = None
        for i, cam in enumerate(cams):
            if i == out["outage_frame"]:
                faults.start_outage()
                recovered_at = faults.outage[1] + recovery_s(s)
            if i == frames - AFTER_FRAMES and recovered_at is not None:
                # unpaced frames can outrun the outage on a fast machine: let it end, so the
                # last AFTER_FRAMES frames (25 of them waited) all come after recovery
                time.sleep(max(0.0, recovered_at - time.monotonic()) + 0.01)
            waited = i % 50 == 0 or i == frames - 1
            f = s.update(cam, 1 / 60, wait=waited)
            out["over_budget"] += f.stats.resident_bytes > budget
            if waited:
                after = recovered_at is not None and time.monotonic() > recovered_at
                out["waited"].append((i, after, f.stats.holes, f.stats.failed_blocks))
                holes = {b for b, (res, _) in f.blocks.items() if res < 0}
                with faults._lock:  # the injector's current post-outage runs of failures
                    runs = {b: faults.streak.get(b, 0) for b in holes}
                out.setdefault("holes", {})[i] = (holes, set(f.failed), runs)
        out["summary"] = s.summary()
        out["last"] = f
    out["threads"] = session_threads()
    return out


def unexplained_holes(run: dict, retries: int = 3) -> list:
    """Waited frames after recovery with a hole that is not a block the session reports
    failed because the injector failed it ``retries`` times in a row after the outage
    (at 5 % a read that happens, rarely, and is reported honestly): the outage not healed."""
    out = []
    for i, after, n_holes, _ in run["waited"]:
        if not after or not n_holes:
            continue
        holes, failed, runs = run["holes"][i]
        fresh = {b for b in failed & holes if runs[b] >= retries}
        if len(holes) != n_holes or holes != fresh:
            out.append((i, sorted(holes), sorted(failed), runs))
    return out


def test_healing_session_survives_faults(store):
    faults = Faults()
    t0 = time.perf_counter()
    run = fly(store, faults)
    elapsed = time.perf_counter() - t0
    summary = run["summary"]
    after = [w for w in run["waited"] if w[1]]
    # the faults really happened, in every kind
    assert faults.counts["fail"] > 0
    assert faults.counts["stall"] > 0
    assert faults.counts["outage"] > 0
    assert summary["io_errors"] >= faults.counts["fail"] + faults.counts["outage"]
    assert len(after) >= 20, f"too few waited frames after the outage: {run['waited'][-3:]}"
    unexplained = unexplained_holes(run)
    assert not unexplained, f"waited frames with holes after recovery: {unexplained}"
    assert run["waited"][-1][0] == FRAMES - 1 and run["waited"][-1][1]  # checked above
    assert run["over_budget"] == 0
    assert summary["peak_resident_bytes"] <= summary["peak_held_bytes"] <= BUDGET_MB * 2**20
    assert summary["frames"] == FRAMES
    assert not run["threads"], f"session threads left after close: {run['threads']}"
    if not LONG:
        assert elapsed < 120  # ~30 s on an idle machine; generous under load


def test_without_retries_the_same_faults_leave_holes(store):
    """Positive control: retries disabled (``heal=False, retries=1``) and the outage's blocks
    are never loaded again, so waited frames after it still have holes or failed blocks."""
    run = fly(store, Faults(), frames=3000, heal=False, retries=1)
    after = [w for w in run["waited"] if w[1]]
    assert len(after) >= 5, run["waited"][-5:]
    assert any(h > 0 for _, _, h, _ in after), run["waited"][-5:]
    assert unexplained_holes(run), "the healing test's hole check misses unhealed holes"
    assert run["summary"]["failed_blocks"]
    assert run["summary"]["hole_frames"] > 0
    assert not run["threads"]


def test_zarr_threads_do_not_grow_across_sessions(store):
    """zarr's shared event-loop threads are zarr's, created once; sessions add none."""

    def others():
        return sorted(t.name for t in threading.enumerate() if t is not threading.main_thread())

    def one_session():
        z0, z1 = store.meta.extra["value_range"]
        cams = default_flythrough(store.grid, z0, z1, 5, 60.0, viewport=(160, 120))
        with open_session(store, budget_mb=8, workers=2) as s:
            for cam in cams:
                s.update(cam, wait=True)

    one_session()
    before = others()
    for _ in range(3):
        one_session()
    assert others() == before
    assert not session_threads()


def test_a_bug_in_a_read_surfaces_instead_of_counting_as_an_io_error(store):
    def buggy(block, level):
        raise KeyError("a bug, not a read error")

    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    with open_session(store, budget_mb=8, workers=1, wait_timeout_s=2.0) as s:
        s._read_hook = buggy
        with pytest.raises(KeyError, match="a bug"):  # noqa: PT012 - raised by a later frame
            for _ in range(3):
                s.update(cam)
                time.sleep(0.05)
        assert s.summary()["io_errors"] == 0


def test_an_undecodable_error_chunk_is_a_read_error_not_a_bug(store, monkeypatch):
    """zarr/numcodecs raise ValueError/RuntimeError for a chunk they cannot decode: counted
    and retried as a read failure (the block is reported failed), not raised as a bug."""
    calls = {"n": 0}
    real = type(store).read_errors

    def broken(self, block):
        calls["n"] += 1
        if block == target:
            raise RuntimeError("error during blosc decompression: -1")
        return real(self, block)

    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(160, 120))[0]
    with open_session(store, budget_mb=8, workers=1, retries=2, backoff_s=0.001) as s:
        target = s.planner.visible(cam)[0]
        monkeypatch.setattr(type(store), "read_errors", broken)
        with pytest.raises(LoadError, match="blosc decompression") as info:  # noqa: PT012
            for _ in range(4):
                s.update(cam, wait=True)
        f = info.value.frame  # the frame the failure was reported with
        assert target in f.failed
        assert f.blocks[target][0] == -1 and f.stats.holes >= 1
        assert s.summary()["io_errors"] >= 2
        assert [list(target)] == s.summary()["failed_blocks"]
