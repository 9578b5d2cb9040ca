"""Loading schemes (``SessionConfig.scheme``): Qiu et al.'s prefetching as published beside
this project's additions (pose-ahead extension, loading at ``tau * lookahead``, several levels
of a block at once), and the reloaded-bytes figure of a session whose budget is exceeded.

Each variant is checked on a pure planner call (no threads, no I/O); the level-by-level rule on
the loader's bookkeeping with ``workers=0`` (no threads)."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal, write_dem
from test_planner import GRID, P, planner

from streamer.cache import LevelCache
from streamer.camera import Camera
from streamer.errors import StreamerError
from streamer.frames import SCHEMES, SessionConfig
from streamer.frustum import block_edge, extension_triangle
from streamer.loader import PER_BLOCK, Loader
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile

CAM = Camera((200.0, 300.0, 200.0), yaw=10, pitch=-20, far=500)  # sees part of the grid
TAU = 4.0


def _velocity(speed: float = 400.0) -> np.ndarray:
    """Moving along the view direction at ``speed`` world units per second."""
    h = np.asarray(CAM.heading, dtype=np.float64)
    return np.array([h[0] * speed, h[1] * speed, 0.0])


def _plan(scheme: str, **kw):
    cfg = SessionConfig(patch_log2=P, tau=TAU, scheme=scheme, **kw)
    pl, _ = planner(cfg)
    visible = set(pl.visible(CAM))
    return pl, visible, pl.prefetch(CAM, _velocity(), visible).wants


def _extension(pl, cam, v) -> set:
    tri = extension_triangle(cam, block_edge(GRID), velocity=v, fps=pl.config.fps)
    return set(pl._existing(tri))


def test_qiu_as_published_plans_this_poses_extension_at_the_needed_level():
    pl, visible, wants = _plan("qiu")
    assert len(pl.poses(CAM, _velocity())) == 1  # no pose ahead
    assert set(wants) == visible | _extension(pl, CAM, _velocity())
    assert len(wants) > len(visible)  # the extension ring is there
    blocks = sorted(wants)
    needed, _ = pl.levels(CAM, blocks, TAU)  # at tau itself: no finer level
    assert {b: lv for b, (lv, _) in wants.items()} == needed
    assert SessionConfig(scheme="qiu").concurrent_levels is False


def test_pose_ahead_adds_the_extension_of_the_pose_ahead():
    pl0, _, qiu = _plan("qiu")
    pl, visible, wants = _plan("qiu+ahead")
    poses = pl.poses(CAM, _velocity())
    assert len(poses) == 2
    ahead = np.asarray(poses[1].position) - np.asarray(CAM.position)
    assert np.allclose(ahead, _velocity() * pl.config.horizon_s)
    assert set(qiu) < set(wants)  # strictly more blocks
    assert set(wants) == visible | _extension(pl, CAM, _velocity()) | _extension(
        pl, poses[1], _velocity()
    )
    # the level is the finer of the two poses' needs at tau (not at a finer tau)
    blocks = sorted(wants)
    here, _ = pl.levels(CAM, blocks, TAU)
    there, _ = pl.levels(poses[1], blocks, TAU)
    assert all(wants[b][0] == max(here[b], there[b]) for b in blocks)
    # horizon 0 is Qiu's plan again
    _, _, none = _plan("qiu+ahead", horizon_s=0.0)
    assert none == qiu


def test_lookahead_plans_the_same_blocks_at_finer_levels():
    _, _, qiu = _plan("qiu")
    pl, _, wants = _plan("qiu+fine")
    assert set(wants) == set(qiu)  # the same extension of this pose only
    blocks = sorted(wants)
    fine, _ = pl.levels(CAM, blocks, TAU * pl.config.lookahead)
    assert {b: lv for b, (lv, _) in wants.items()} == fine
    assert all(wants[b][0] >= qiu[b][0] for b in blocks)
    assert any(wants[b][0] > qiu[b][0] for b in blocks)
    # lookahead 1 is Qiu's plan again
    _, _, same = _plan("qiu+fine", lookahead=1.0)
    assert same == qiu


@pytest.mark.parametrize("scheme", ["qiu+ahead+fine", "ours"])
def test_both_additions_plan_the_union_at_finer_levels(scheme):
    _, _, ahead = _plan("qiu+ahead")
    _, _, fine = _plan("qiu+fine")
    pl, _, wants = _plan(scheme)
    assert set(wants) == set(ahead)
    assert all(wants[b][0] >= ahead[b][0] for b in wants)
    assert all(wants[b][0] >= fine[b][0] for b in fine)
    assert any(wants[b][0] > ahead[b][0] for b in wants)
    assert pl.config.concurrent_levels is (scheme == "ours")


@pytest.mark.parametrize("scheme", list(SCHEMES))
def test_without_prefetch_every_scheme_plans_the_visible_set_only(scheme):
    pl, visible, wants = _plan(scheme, prefetch=False)
    assert set(wants) == visible
    needed, _ = pl.levels(CAM, sorted(visible), TAU)
    assert {b: lv for b, (lv, _) in wants.items()} == needed


def test_an_unknown_scheme_is_refused_with_the_choices():
    with pytest.raises(StreamerError, match=r"'qiu-ish'.*qiu, qiu\+ahead"):
        SessionConfig(scheme="qiu-ish")


# -- the loader: level by level, and reloaded bytes -----------------------------------------


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("schemes")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 3), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, executor="threads"))


def _cameras(store, frames: int, speed: float | None = None):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, frames, 60.0, speed=speed, viewport=(320, 240))


@pytest.mark.parametrize("scheme", ["qiu", "qiu+ahead+fine", "ours"])
def test_levels_of_a_block_are_fetched_one_at_a_time_unless_concurrent(store, scheme):
    cam = _cameras(store, 1)[0]
    # workers=0 and a 1-byte allowance: the first update reads the error fields and one level
    with open_session(
        store, budget_mb=16, workers=0, tau=0.25, scheme=scheme, inline_bytes_per_frame=1
    ) as s:
        s.update(cam)
        ld = s.loader
        with ld.cv:
            deep = [
                b
                for b, want, _pin, _p in ld.cache.wanted()
                if b in ld.errors and want - ld.cache.level(b) >= PER_BLOCK + 1
            ]
            assert deep, "some block still misses several levels"
            b = deep[0]
            taken = []
            while (lv := ld._take(b)) is not None:
                taken.append(lv)
            first = ld.cache.level(b) + 1
    if scheme == "ours":
        assert taken == list(range(first, first + PER_BLOCK))
    else:
        assert taken == [first]  # the next level waits until this one is decoded


def _fly_out_and_back(store, budget_mb: float, scheme: str = "ours"):
    cams = _cameras(store, 40, speed=9000.0)
    with open_session(store, budget_mb=budget_mb, workers=0, tau=2.0, scheme=scheme) as s:
        for cam in cams + cams[::-1]:
            s.update(cam, wait=True)
        return s.summary(), s.loader.ever_loaded, s.level_bytes


@pytest.mark.parametrize("scheme", ["qiu", "ours"])
def test_a_budget_smaller_than_the_flight_reloads_and_counts_it(store, scheme):
    small, ever, level_bytes = _fly_out_and_back(store, 0.05, scheme)
    assert small["peak_held_bytes"] <= small["budget_bytes"]
    assert small["reloaded_bytes"] > 0 and small["reloaded_levels"] > 0
    # every byte loaded is a first load of its (block, level) or a reload
    first = sum(level_bytes[lv] for _b, lv in ever)
    assert small["loaded_bytes"] == first + small["reloaded_bytes"]
    # the quiet case: a budget that holds the whole flight never reloads
    big, ever_big, _ = _fly_out_and_back(store, 64.0, scheme)
    assert big["reloaded_bytes"] == 0 and big["reloaded_levels"] == 0
    assert big["loaded_bytes"] == sum(level_bytes[lv] for _b, lv in ever_big)


class _Thrash(Exception):
    pass


def _most_jobs_in_a_frame(store, monkeypatch, limit: int) -> int:
    """Most block reads one frame ran on a flight out and back under a budget far smaller than
    the flight (``workers=0``: frames load inline until their queue is empty); stops with
    ``_Thrash`` once a frame runs more than ``limit``."""
    jobs = [0]
    run_job = Loader.run_job

    def counted(self, job):
        jobs[0] += 1
        if jobs[0] > limit:
            raise _Thrash
        return run_job(self, job)

    monkeypatch.setattr(Loader, "run_job", counted)
    cams = _cameras(store, 40, speed=9000.0)
    most = 0
    with open_session(store, budget_mb=0.05, workers=0, tau=2.0) as s:
        for cam in cams + cams[::-1]:
            jobs[0] = 0
            s.update(cam, wait=True)
            most = max(most, jobs[0])
    return most


def test_prefetch_never_evicts_a_more_important_prefetch(store, monkeypatch):
    assert _most_jobs_in_a_frame(store, monkeypatch, 400) <= 400
    # positive control: without the guard, prefetch loads evict each other and load again
    # (measured on a 60-frame version of this flight: 931 reads in one frame, 10.2 MB loaded
    # instead of 0.75 MB)
    monkeypatch.setattr(LevelCache, "room_for", lambda self, block, nbytes: True)
    with pytest.raises(_Thrash):
        _most_jobs_in_a_frame(store, monkeypatch, 400)
