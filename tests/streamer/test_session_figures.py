"""A session's figures agree with each other: per-frame resident bytes against the summary's
peak, the budget error's floor and its MiB, the frame interval ``dt``."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from demtools import fractal, write_dem

from streamer.camera import Camera
from streamer.errors import BudgetError
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 4 x 5 blocks of 65 samples (10 m cells)."""
    tmp = tmp_path_factory.mktemp("figures")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 7), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=1))


def over(store, fx: float, fy: float, z: float = 900.0, pitch: float = -60.0) -> Camera:
    """A camera at fractions ``(fx, fy)`` of the store's extent looking north."""
    x0, y0, x1, y1 = store.grid.extent
    pos = (x0 + fx * (x1 - x0), y0 + fy * (y1 - y0), z)
    return Camera(pos, pitch=pitch, fov_y=50, viewport=(160, 120), near=1.0, far=5000.0)


def wait_until(cond, timeout_s: float = 10.0) -> bool:
    """Poll ``cond`` every 5 ms for at most ``timeout_s``; its last answer."""
    end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    return cond()


def test_frame_resident_bytes_exclude_reads_in_flight(store):
    """A frame taken while level reads are reserved reports the levels held, never more than
    the summary's peak of them (it counted the reservations too)."""
    gate = threading.Event()
    blocked = {"on": False}

    def hook(block, level):
        if blocked["on"] and level >= 0:
            gate.wait(10.0)  # bounded: the test releases it

    a, b = over(store, 0.2, 0.05), over(store, 0.8, 0.6)
    with open_session(store, budget_mb=64, workers=1) as s:
        s._read_hook = hook
        try:  # (the gate opened before the session closes: close waits for the reads)
            s.warm_up(a)
            first = s.update(a, wait=True)
            blocked["on"] = True
            s.update(b)  # new blocks: their level reads start and block in the hook
            assert wait_until(lambda: s.cache.reserved > 0)
            f = s.update(b)
            held = s.cache.nbytes - s.cache.reserved
            summary = s.summary()
        finally:
            gate.set()
    assert f.stats.resident_bytes == held
    assert f.stats.resident_bytes <= summary["peak_resident_bytes"]
    assert first.stats.resident_bytes <= summary["peak_resident_bytes"]
    frames_peak = max(first.stats.resident_bytes, f.stats.resident_bytes)
    assert summary.get("peak_resident_bytes_frames") == frames_peak


def test_frame_resident_bytes_without_reads_in_flight(store):
    """Positive control: with nothing in flight a frame's resident bytes are the cache's."""
    with open_session(store, budget_mb=64, workers=1) as s:
        f = s.update(over(store, 0.5, 0.3), wait=True)
        assert wait_until(lambda: s.cache.reserved == 0)
        f = s.update(over(store, 0.5, 0.3), wait=True)
        assert f.stats.resident_bytes == s.cache.nbytes - s.cache.reserved > 0
        assert f.stats.resident_bytes <= s.summary()["peak_resident_bytes"]


@pytest.fixture(scope="module")
def holey_store(tmp_path_factory):
    """Nodata in every 65² block: under the rule 'full' each stays at full resolution."""
    tmp = tmp_path_factory.mktemp("holes")
    data = fractal((193, 193), 4).astype(np.float32)
    data[20::64, 20::64] = np.nan
    src = write_dem(tmp / "d.tif", data, cell=10.0, nodata=float("nan"))
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=1))


MIB = re.compile(r"([\d.]+) MiB \(([\d,]+) bytes\)")


def figures(message: str) -> list[tuple[str, int]]:
    """Every ``X MiB (N bytes)`` of a message as ``(X, N)``."""
    return [(x, int(n.replace(",", ""))) for x, n in MIB.findall(message)]


def test_budget_floor_before_the_error_tables_suffices(holey_store):
    """A budget error raised in warm-up, before any block's error table was read, gives a
    floor that suffices: a session with that budget (and any τ) draws the view; each byte count
    reads as one MiB figure, rounded up so that budget holds it."""
    cam = over(holey_store, 0.5, 0.1, z=700.0)
    with open_session(holey_store, budget_mb=64, workers=1) as s:
        patch = s.planner.needed(cam)  # no table read: the patch levels
        assert patch
        patch_bytes = sum(s._cum_bytes[lv] for lv in patch.values())
    with (
        open_session(holey_store, budget_mb=(patch_bytes - 1) / 2**20, workers=1) as s,
        pytest.raises(BudgetError, match="at any tau") as err,
    ):
        s.warm_up(cam)
    message = str(err.value)
    floor = int(
        re.search(r"at least [\d.]+ MiB \(([\d,]+) bytes\)", message).group(1).replace(",", "")
    )
    with open_session(holey_store, budget_mb=floor / 2**20, workers=1, tau=1e6) as s:
        s.warm_up(cam)
        assert s.update(cam, wait=True).blocks  # the floor given is enough
    for x, n in figures(message):
        assert int(float(x) * 2**20) >= n  # a budget of X MiB holds N bytes
        assert float(x) * 2**20 <= n * (1 + 1e-3)  # 4 significant digits, not 2 decimals


def test_budget_error_with_a_larger_tau_that_fits(store):
    """Positive control: without nodata a larger τ fits, and the error says so."""
    cam = over(store, 0.5, 0.1, z=700.0)
    with (  # noqa: PT012 - the first frame needs patch levels; then the errors ask for more
        open_session(store, budget_mb=0.03, workers=1, tau=0.01) as s,
        pytest.raises(BudgetError, match="raise budget_mb or the error threshold tau") as err,
    ):
        for _ in range(3):
            s.update(cam, wait=True)
    for x, n in figures(str(err.value)):
        assert int(float(x) * 2**20) >= n


@pytest.mark.parametrize("dt", [float("nan"), -0.01, float("inf"), "soon"])
def test_update_refuses_a_bad_dt(store, dt):
    """A NaN, negative, infinite or non-numeric ``dt`` is refused, naming it, on any frame."""
    cam = over(store, 0.5, 0.3)
    with open_session(store, budget_mb=64, workers=0) as s:
        with pytest.raises(ValueError, match=r"\bdt must be"):
            s.update(cam, dt)
        s.update(cam)
        with pytest.raises(ValueError, match=r"\bdt must be"):
            s.update(cam, dt)
        assert s.summary()["frames"] == 1


@pytest.mark.parametrize("dt", [None, 0.0, 1 / 60, 2])
def test_update_takes_a_good_dt(store, dt):
    """Positive control: no dt, 0 (the same instant) and positive intervals are taken."""
    cam = over(store, 0.5, 0.3)
    with open_session(store, budget_mb=64, workers=0) as s:
        s.update(cam, dt)
        s.update(cam, dt)
        assert s.summary()["frames"] == 2
