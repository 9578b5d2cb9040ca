"""The session's lock discipline (issue 14): the caller's thread only plans (no read, no
decode), and no thread reads, decodes or plans while holding the lock ``update()`` waits on;
holds are recorded by :mod:`streamer.lockprobe`. The positive control is a loader that reads
while holding the lock."""

from __future__ import annotations

import time

import pytest
from demtools import fractal, write_dem

from streamer.lockprobe import install
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("locks")
    src = write_dem(tmp / "d.tif", fractal((257, 385), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=2))


def _fly(s, store, probe, frames: int = 150) -> None:
    z0, z1 = store.meta.extra["value_range"]
    cams = default_flythrough(store.grid, z0, z1, frames, 60.0, viewport=(320, 240))
    s.warm_up(cams[0])  # (plans the prefetch on the caller's thread, as documented)
    probe.calls.clear()
    for i, cam in enumerate(cams):
        s.update(cam, 1 / 60, wait=i % 10 == 0)  # some frames wait on the condition


def test_no_read_decode_or_planning_under_the_lock(store):
    with open_session(store, budget_mb=4, workers=3) as s:
        probe = install(s)
        _fly(s, store, probe)
        roles = probe.by_role()
    assert probe.violations == []
    what = {w for _, w in probe.calls}
    assert {"read_level_raw", "decode_next", "planner.needed", "planner.prefetch"} <= what
    by_caller = {w for name, w in probe.calls if name == "MainThread"}
    assert by_caller == {"planner.needed"}  # update() plans the visible set, nothing else
    assert len(roles["caller"]) > 150 and len(roles["loader"]) > 50 and roles["planner"]


def test_positive_control_a_loader_reading_under_the_lock_is_caught(store):
    with open_session(store, budget_mb=4, workers=3) as s:
        probe = install(s)
        read = s.store.read_level_raw  # the probed read

        def slow_read(b, level):
            with s.loader.cv:  # a loader that holds the session lock while it reads
                time.sleep(0.002)
                return read(b, level)

        s.store.read_level_raw = slow_read
        _fly(s, store, probe, frames=30)
        roles = probe.by_role()
    assert probe.violations and {w for _, w in probe.violations} == {"read_level_raw"}
    assert all(name.startswith("terrastream-load") for name, _ in probe.violations)
    assert max(wall for wall, _ in roles["loader"]) >= 0.002  # the sleep is inside a hold
