"""Audit 44 (streaming): block ids outside the grid are refused by the session's and the
cache's public lookups, and a level a frame lacks counts as real-time even when it arrives
before the frame is finished (it counted as prefetched, prefetch off too)."""

from __future__ import annotations

import json
import re
import threading
import time

import numpy as np
import pytest
from demtools import fractal, write_dem

from streamer.cache import LevelCache
from streamer.camera import Camera
from streamer.errors import BudgetError
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.errors import LayoutError
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 129 x 193 store of 4 x 6 blocks of 33 samples (10 m cells)."""
    tmp = tmp_path_factory.mktemp("audit44")
    src = write_dem(tmp / "d.tif", fractal((129, 193), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1))


def over(store, fx: float, fy: float, z: float = 900.0) -> Camera:
    """A camera at fractions ``(fx, fy)`` of the store's extent looking north, down."""
    x0, y0, x1, y1 = store.grid.extent
    pos = (x0 + fx * (x1 - x0), y0 + fy * (y1 - y0), z)
    return Camera(pos, pitch=-50.0, fov_y=50, viewport=(160, 120), near=1.0, far=5000.0)


OUTSIDE = [(-1, -1), (-1, 0), (0, -1), (4, 0), (0, 6), (10**9, 0)]


@pytest.mark.parametrize("block", OUTSIDE)
def test_session_lookups_refuse_a_block_outside_the_grid(store, block):
    """``levels((-1, -1))`` returned [] and ``block_side`` None: a wrong id read as a block
    holding nothing. Now a ValueError naming the block and the grid."""
    assert store.grid.shape == (4, 6)
    with open_session(store, budget_mb=16, workers=1) as s:
        s.update(over(store, 0.5, 0.1), wait=True)
        for call in (s.levels, s.block_side, s.cache.level, s.cache.want, s.cache.levels):
            with pytest.raises(ValueError, match=r"outside the 4x6-block grid") as info:
                call(block)
            assert isinstance(info.value, LayoutError)
            assert repr(block) in str(info.value)


@pytest.mark.parametrize("block", [(1.5, 0), ("a", 0), (0,), None])
def test_session_lookups_refuse_what_is_no_block_id(store, block):
    with open_session(store, budget_mb=16, workers=1) as s, pytest.raises(LayoutError):
        s.levels(block)


def test_session_lookups_of_blocks_inside_the_grid_answer(store):
    """The quiet case: every block inside the grid answers, loaded or not, numpy ids too."""
    with open_session(store, budget_mb=16, workers=1) as s:
        f = s.update(over(store, 0.5, 0.1), wait=True)
        shown = [b for b, (have, _) in f.blocks.items() if have >= 0]
        assert shown
        for b in store.grid.blocks():
            n = len(s.levels(b))
            assert n == s.cache.level(b) + 1
            s.block_side(b)
        b = shown[0]
        assert len(s.levels((np.int64(b[0]), np.int64(b[1])))) == len(s.levels(b)) > 0


def test_cache_refuses_pins_and_levels_of_a_block_outside_its_grid():
    """A cache given its grid refuses a new pin, want or level outside it, changing nothing;
    a cache without one (tests, tools) checks nothing, as before."""
    c = LevelCache(10_000, (2, 3))
    c.set_pins({(0, 0): 0}, [8, 32])
    with pytest.raises(LayoutError, match=r"\(2, 0\) is outside the 2x3-block grid"):
        c.set_pins({(0, 0): 0, (2, 0): 0}, [8, 32])
    assert c.want((0, 0)) == (0, 0)  # unchanged by the refused call
    with pytest.raises(LayoutError, match="outside"):
        c.set_prefetch({(0, -1): (1, 1.0)})
    with pytest.raises(LayoutError, match="outside"):
        c.add_level((5, 5), 0, np.zeros(1))
    with pytest.raises(LayoutError, match="outside"):
        c.drop_level((-1, -1))
    with pytest.raises(ValueError, match="holds no level"):
        c.drop_level((1, 1))
    assert c.add_level((0, 0), 0, np.zeros(1))
    unchecked = LevelCache(10_000)
    assert unchecked.levels((-1, -1)) == [] and unchecked.level((-1, -1)) == -1


def _settle(session):
    """Make every read the session starts finish before ``update`` goes on: a store that
    answers within the frame (the race a fast local store runs every frame)."""
    ld = session.loader
    pump = ld.pump
    caller = threading.get_ident()

    def pump_and_wait() -> None:
        pump()
        if threading.get_ident() != caller:
            return  # (a loader pumps too, from its completion callback)
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            with ld.cv:
                if not ld.busy():
                    return
            time.sleep(0.002)

    ld.pump = pump_and_wait


def test_a_level_arriving_within_its_frame_is_real_time_not_prefetched(store):
    """Prefetch off, the error tables read, one frame of new blocks whose reads all finish
    inside ``update``: their bytes were loaded for that frame, in real time. They counted as
    prefetched (the levels were marked demanded only after the reads had arrived)."""
    cam = over(store, 0.5, 0.1)
    with open_session(store, budget_mb=16, workers=1, prefetch=False) as s:
        s._read_error_tables(store.grid.blocks())
        _settle(s)
        f = s.update(cam)
        summary = s.summary()
    assert not f.stats.stalled  # (all arrived before the frame was finished)
    assert f.stats.realtime_bytes > 0
    assert f.stats.prefetched_bytes == 0
    assert f.stats.late_bytes == 0  # arrived before the frame was shown: not late
    assert summary["prefetched_bytes"] == 0


def test_prefetch_on_still_counts_what_is_read_ahead(store):
    """The control: with prefetch on, the ring around the view is read ahead and counted as
    prefetched, beside the frame's own real-time bytes."""
    cam = over(store, 0.5, 0.1)
    with open_session(store, budget_mb=16, workers=1) as s:
        s._read_error_tables(store.grid.blocks())
        _settle(s)
        f = s.update(cam)
        pre = f.stats.prefetched_bytes
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not pre:  # the plan runs on its own thread
            time.sleep(0.02)
            pre = s.update(cam, 0.0).stats.prefetched_bytes
    assert f.stats.realtime_bytes > 0
    assert pre > 0


def test_stream_warns_of_frames_that_saw_no_block(tmp_path, store):
    """A path that leaves the DEM: most frames see nothing, need nothing and cannot stall,
    and the summary read as a perfect flight. Now a warning and ``unseen_frames`` say so."""
    from typer.testing import CliRunner

    from cli.main import app

    x0, y0, x1, y1 = store.grid.extent
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    path = tmp_path / "p.csv"  # from the middle, 200 km east, looking east and down
    path.write_text(f"t,x,y,z,yaw,pitch\n0,{cx},{cy},900,0,-40\n1,{cx + 2e5},{cy},900,0,-40\n")
    out = tmp_path / "s.json"
    args = ["stream", store.url, "--path", path, "--frames", 20, "--size", "64x48"]
    r = CliRunner().invoke(app, [str(a) for a in [*args, "--json", out]])
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    unseen = sum(1 for row in d["frames"] if not row["visible_blocks"])
    assert 0 < unseen < 20
    assert d["summary"]["unseen_frames"] == unseen
    assert f"{unseen} of 20 frame(s) had no block of the DEM in view" in r.output


def test_stream_says_nothing_of_unseen_frames_when_every_frame_sees(tmp_path, store):
    """The quiet case: the default fly-through sees the DEM in every frame."""
    from typer.testing import CliRunner

    from cli.main import app

    out = tmp_path / "s.json"
    args = ["stream", store.url, "--frames", 10, "--size", "64x48", "--json", out]
    r = CliRunner().invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    d = json.loads(out.read_text())
    assert all(row["visible_blocks"] for row in d["frames"])
    assert d["summary"]["unseen_frames"] == 0
    assert "no block of the DEM in view" not in r.output


def test_a_second_close_names_the_threads_still_running(store):
    """A read that hangs outlives ``close(0.2)``, which names its thread; closing again
    answered [] while that thread still ran. Now it waits again (bounded) and names it, and
    once the read ends a close answers [] and ``unfinished`` is emptied."""
    gate, entered = threading.Event(), threading.Event()

    def hook(block, level):
        if level >= 0:
            entered.set()
            gate.wait(10.0)  # bounded: the test opens it

    s = open_session(store, budget_mb=16, workers=1)
    s._read_hook = hook
    try:
        s.update(over(store, 0.5, 0.1))
        deadline = time.monotonic() + 5.0
        while not entered.wait(0.05) and time.monotonic() < deadline:
            s.update(over(store, 0.5, 0.1), 0.0)  # (the levels queue once the errors are in)
        assert entered.is_set()
        first = s.close(0.2)
        assert first and all(n.startswith("terrastream-load") for n in first)
        assert s.close(0.2) == first
        assert s.unfinished == first
    finally:
        gate.set()
    assert s.close(5.0) == []
    assert s.unfinished == []
    assert not [t for t in threading.enumerate() if t.name in first]


def test_closing_twice_without_a_hung_read_answers_nothing_left(store):
    """The quiet case: no thread outlives the first close; the second answers [] at once,
    and a ``with`` block closed inside it does not wait again on exit."""
    with open_session(store, budget_mb=16, workers=2) as s:
        s.update(over(store, 0.5, 0.1), wait=True)
        assert s.close() == []
        t0 = time.monotonic()
        assert s.close() == []
        assert time.monotonic() - t0 < 1.0
    assert not [t for t in threading.enumerate() if t.name.startswith("terrastream-")]


def _bytes(pattern: str, text: str) -> int:
    m = re.search(pattern, text)
    assert m, text
    return int(m.group(1).replace(",", ""))


@pytest.fixture(scope="module")
def big_blocks(tmp_path_factory):
    """A 257 x 257 store of 2 x 2 blocks of 129 samples: more levels than the patch level."""
    tmp = tmp_path_factory.mktemp("audit44big")
    src = write_dem(tmp / "d.tif", fractal((257, 257), 3), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=129, workers=1))


def first_of_default(store) -> Camera:
    """The default fly-through's first camera: low over the DEM, a block beneath it."""
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, 5, 60.0, viewport=(160, 120))[0]


def test_a_budget_error_never_says_a_view_needs_less_than_its_floor(big_blocks):
    """Frame 0, error tables not read: the pins count every block at its coarsest levels, and
    the error said "need 1,156 bytes at their levels ... at any tau at least 33,860 bytes".
    The need is now counted at the levels the read tables ask for, never below the floor."""
    store = big_blocks
    cam = first_of_default(store)
    s = open_session(store, budget_mb=100 / 2**20, workers=1)
    with s, pytest.raises(BudgetError) as info:
        s.update(cam, wait=True)
    text = str(info.value)
    need = _bytes(r"need [\d.]+ MiB \(([\d,]+) bytes\) at their levels", text)
    floor = _bytes(r"at least [\d.]+ MiB \(([\d,]+) bytes\)", text)
    assert floor > 100
    assert need >= floor


def test_a_budget_error_of_a_known_view_keeps_its_need(big_blocks):
    """The quiet case: the tables read (a session that streamed the view before), the need
    said is the frame's own, as the pins counted it."""
    store = big_blocks
    cam = first_of_default(store)
    with open_session(store, budget_mb=64, workers=1) as s:
        f = s.update(cam, wait=True)
        s._read_error_tables(store.grid.blocks())
        s.update(cam, wait=True)
        need_known = s.update(cam).stats.needed_bytes
    with open_session(store, budget_mb=100 / 2**20, workers=1) as s:
        s._read_error_tables(store.grid.blocks())
        with pytest.raises(BudgetError) as info:
            s.update(cam)
    assert f.stats.visible_blocks
    text = str(info.value)
    assert _bytes(r"need [\d.]+ MiB \(([\d,]+) bytes\) at their levels", text) == need_known
