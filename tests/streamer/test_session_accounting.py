"""Stall accounting named by set, late bytes (independent of stalls) and frames drawn coarser
than needed (issue 10 item 5)."""

from __future__ import annotations

import pytest
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("acct")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 9), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def cams(store, n, speed=None):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=speed, viewport=(320, 240))


@pytest.mark.parametrize(("culling", "name"), [("qiu", "triangle"), ("hull", "hull")])
def test_stalls_name_the_set_they_count(store, culling, name):
    with open_session(store, budget_mb=16, workers=1, culling=culling) as s:
        f = s.update(cams(store, 1)[0])
        assert f.stats.stall_set == name
        assert s.summary()["stall_set"] == name


def test_a_waited_frame_does_not_stall_but_its_bytes_are_late(store):
    """Late bytes are not stalls: frame 0 waits (no stall), its data arrives after it was due."""
    with open_session(store, budget_mb=16, workers=2, latency_ms=2) as s:
        f = s.update(cams(store, 1)[0], wait=True)
    assert not f.stats.stalled
    assert f.stats.levels_short == 0
    assert f.stats.late_bytes > 0
    assert f.stats.late_bytes <= f.stats.realtime_bytes


def test_frames_asked_ahead_of_their_due_time_stall_without_late_bytes(store):
    """The other way round: a loop that runs ahead of the frame clock (fps=1: frame i is due
    i seconds after frame 0) stalls, but nothing arrives after its frame was due."""
    path = cams(store, 40, speed=3000.0)
    with open_session(store, budget_mb=16, workers=1, fps=1.0, latency_ms=3) as s:
        first = s.update(path[0], wait=True).stats
        rows = [s.update(c, 1 / 60).stats for c in path[1:]]
        summary = s.summary()
    stalled = [r for r in rows if r.stalled]
    assert stalled, "the flight must outrun the loader"
    assert all(r.levels_short > 0 for r in stalled)
    assert all(r.levels_short == 0 for r in rows if not r.stalled)
    assert sum(r.late_bytes for r in rows) == 0
    assert summary["late_bytes"] == first.late_bytes  # only frame 0's waited-for bytes
    by_levels = summary["coarse_frames_by_levels"]
    assert sum(by_levels.values()) == len(stalled)
    assert max(int(k) for k in by_levels) == max(r.levels_short for r in stalled)


def test_a_hole_counts_one_level_more_than_needed(store):
    with open_session(store, budget_mb=16, workers=1, latency_ms=20) as s:
        f = s.update(cams(store, 1)[0])  # nothing resident yet
    assert f.stats.holes == f.stats.visible_blocks > 0
    assert f.stats.levels_short == max(need for _, need in f.blocks.values()) + 1


def test_account_hull_counts_stalls_over_the_drawn_set_too(store):
    """A qiu-culling session with ``account_hull`` also says whether the hull set (what the
    renderer draws) had all its levels; deterministic with ``workers=0`` (nothing loads after
    update() returns), so each frame's figure is checked against the cache."""
    path = cams(store, 30, speed=3000.0)
    opts = {"workers": 0, "inline_bytes_per_frame": 3000, "account_hull": True}
    rows, expected = [], []
    with open_session(store, budget_mb=16, **opts) as s:
        for i, c in enumerate(path):
            rows.append(s.update(c, 1 / 60, wait=i == 0).stats)
            hull = s.planner.needed(c, culling="hull")
            expected.append(
                any(s.cache.level(b) < lv or b not in s.loader.errors for b, lv in hull.items())
            )
        summary = s.summary()
    assert [r.hull_stalled for r in rows] == expected
    assert any(expected) and not all(expected)  # the flight exercises both cases
    assert summary["stall_frames_hull"] == sum(expected)
    with open_session(store, budget_mb=16, workers=1) as s:
        assert s.update(path[0]).stats.hull_stalled is None
        assert s.summary()["stall_frames_hull"] is None
