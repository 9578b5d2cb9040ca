"""The pure parts of a session: the planner (blocks and levels for a pose), the load queue
(keys, cancellation, backoff, healing), the quadtree geometry helper, and Session.set_tau."""

from __future__ import annotations

import numpy as np
import pytest
from test_levels import CAMERAS, _field

from streamer.errors import StreamerError
from streamer.frames import SessionConfig
from streamer.levels import PatchErrorTable
from streamer.loadqueue import LoadQueue
from streamer.planner import Planner
from tiler.grid import BlockGrid
from tiler.quadtree import block_zranges, half_diagonal, node_centres, split_children

K, P = 7, 2
GRID = BlockGrid(height=8 * 128 + 1, width=8 * 128 + 1, k=K, x0=0.0, y0=1000.0, dx=1.5, dy=1.5)


def planner(config: SessionConfig, with_errors: bool = True) -> tuple[Planner, PatchErrorTable]:
    rng = np.random.default_rng(0)
    exists = np.ones((8, 8), bool)
    exists[0, 0] = False
    zmin = rng.random((8, 8)) * 50
    zmax = zmin + 100
    zmin[0, 0] = zmax[0, 0] = np.nan
    table = PatchErrorTable(K, config.patch_log2)
    if with_errors:
        for r in range(8):
            for c in range(8):
                table.add((r, c), _field(rng, K, 4))
    return Planner(GRID, K, exists, zmin, zmax, table, config), table


def test_needed_is_the_visible_set_at_the_table_levels():
    cfg = SessionConfig(patch_log2=P, tau=20.0)
    pl, table = planner(cfg)
    cam = CAMERAS[0]
    needed = pl.needed(cam)
    assert needed, "the oblique camera sees blocks"
    assert (0, 0) not in needed  # a block without terrain is never planned
    assert set(needed) == set(pl.visible(cam))
    blocks = sorted(needed)
    zr = block_zranges(pl.zr[..., 0], pl.zr[..., 1], np.array(blocks))
    ref, _ = table.needed_levels(GRID, blocks, cam, 20.0, "qiu", zr)
    assert [needed[b] for b in blocks] == ref.tolist()
    finer = pl.needed(cam, tau=0.5)
    assert all(finer[b] >= needed[b] for b in blocks)
    assert any(finer[b] > needed[b] for b in blocks)


def test_blocks_without_errors_need_the_patch_level():
    pl, _ = planner(SessionConfig(patch_log2=P), with_errors=False)
    needed = pl.needed(CAMERAS[0])
    assert needed
    assert set(needed.values()) == {P}


def _join(pl: Planner, levels: dict) -> dict:
    """``levels`` raised where a neighbour is too fine to join, as a dict (the reference)."""
    if len(levels) < 2:
        return levels
    blocks = list(levels)
    lv = np.fromiter(levels.values(), dtype=np.int64, count=len(blocks))
    out = pl._restrict(np.asarray(blocks, dtype=np.int64), lv)
    return dict(zip(blocks, out.tolist(), strict=True))


def _levels_reference(pl: Planner, camera, blocks, tau, with_rho=True):
    """``Planner.levels`` as it was computed block by block (known blocks listed, dicts)."""
    floor = min(pl.config.patch_log2, pl.k)
    needed = dict.fromkeys(blocks, floor)
    rho = dict.fromkeys(blocks, 0.0) if with_rho else {}
    have = pl.errors.known(blocks)
    if have:
        ids = np.asarray(have, dtype=np.int64).reshape(-1, 2)
        zr = pl.zr[ids[:, 0], ids[:, 1]]
        lv, r = pl.errors.needed_levels(
            pl.grid, have, camera, tau, pl.config.metric, zr, with_rho=with_rho
        )
        needed.update(zip(have, lv.tolist(), strict=True))
        needed = (
            dict(zip(have, pl._restrict(ids, lv).tolist(), strict=True))
            if len(have) == len(blocks)
            else _join(pl, needed)
        )
        if with_rho:
            rho.update(zip(have, r.tolist(), strict=True))
    return needed, rho


@pytest.mark.parametrize("known", [1.0, 0.7, 0.2, 0.0])
@pytest.mark.parametrize("tau", [0.5, 4.0, 40.0])
def test_needed_arrays_equal_the_per_block_levels(known, tau):
    """``needed`` / ``needed_arrays`` / ``levels`` (one lookup of every block's slot) give
    what the block-by-block reference gives, with all, some or none of the errors known."""
    pl, table = planner(SessionConfig(patch_log2=P, tau=tau))
    rng = np.random.default_rng(int(known * 10))
    for b in [(r, c) for r in range(8) for c in range(8)]:
        if rng.random() >= known:
            table.remove(b)
    for cam in CAMERAS:
        blocks, lv = pl.needed_arrays(cam)
        assert blocks == pl.visible(cam) and lv.dtype == np.int64
        ref = _levels_reference(pl, cam, blocks, tau, with_rho=False)[0]
        assert dict(zip(blocks, lv.tolist(), strict=True)) == ref == pl.needed(cam)
        assert list(ref) == blocks
        assert pl.levels(cam, blocks, tau, with_rho=False) == (ref, {})
        assert pl.levels(cam, blocks, tau) == _levels_reference(pl, cam, blocks, tau)


def test_needed_arrays_control_sees_slots_out_of_order(monkeypatch):
    """The control: with each block's slot lookup answered for another block, the
    comparison above fails."""
    pl, _ = planner(SessionConfig(patch_log2=P, tau=4.0))
    lookup = PatchErrorTable.lookup
    differ = []
    for cam in CAMERAS:
        blocks, _ = pl.needed_arrays(cam)
        ref = _levels_reference(pl, cam, blocks, 4.0, with_rho=False)[0]
        with monkeypatch.context() as m:
            m.setattr(PatchErrorTable, "lookup", lambda self, b: lookup(self, b)[::-1].copy())
            blocks, lv = pl.needed_arrays(cam)
        differ.append(dict(zip(blocks, lv.tolist(), strict=True)) != ref)
    assert any(differ)


@pytest.mark.parametrize("prefetch", [True, False])
def test_prefetch_plan_holds_the_visible_set_and_a_ring(prefetch):
    cfg = SessionConfig(patch_log2=P, prefetch=prefetch)
    pl, _ = planner(cfg)
    cam = CAMERAS[0]
    visible = set(pl.visible(cam))
    plan = pl.prefetch(cam, np.array([30.0, 0.0, 0.0]), visible)
    assert visible <= set(plan.wants)
    assert plan.ring == len(plan.wants) - len(visible)
    assert (plan.ring > 0) == prefetch
    assert len(pl.poses(cam, np.array([30.0, 0.0, 0.0]))) == (2 if prefetch else 1)
    assert len(pl.poses(cam, None)) == 1
    # loading ahead at tau * lookahead: never coarser than what the frame needs
    needed = pl.needed(cam)
    assert all(plan.wants[b][0] >= lv for b, lv in needed.items())


def test_queue_orders_by_key_and_counts_cancellations():
    q = LoadQueue(retries=3, backoff_s=0.1, max_backoff_s=1.0)
    q.push((0, 1), (1, 0))
    q.push((0, 2), (0, 5))
    q.push((0, 3), (2, 0))
    assert q.pop(0.0, lambda b: "job") == ((0, 2), "job")
    assert q.pop(0.0, lambda b: None if b == (0, 1) else "job") == ((0, 3), "job")  # (0,1) dropped
    assert len(q) == 0
    q.push((1, 1), (0,))
    q.rebuild([((0,), (2, 2))])
    assert q.cancelled == 1


def test_queue_backoff_doubles_caps_and_heals():
    q = LoadQueue(retries=3, backoff_s=0.1, max_backoff_s=0.3)
    b = (4, 4)
    delays = []
    for n in range(1, 6):
        assert q.failed_read(b, 10.0) == n
        delays.append(round(q.retry_at[b] - 10.0, 6))
    assert delays == [0.1, 0.2, 0.3, 0.3, 0.3]
    assert q.is_failed(b) and q.failed_blocks() == {b}
    q.push(b, (0,))
    assert q.pop(10.0, lambda b: "job") is None  # backing off: stays queued
    assert len(q) == 1
    assert q.pop(10.5, lambda b: "job") == (b, "job")  # healing: still retried
    assert q.given_up(b, since=9.0)  # 5 failures since: more than a round of 3
    assert not q.given_up(b, since=11.0)
    q.failed_read(b, 12.0)
    q.failed_read(b, 12.5)
    assert not q.given_up(b, since=11.0)  # 2 of a fresh round of 3
    q.failed_read(b, 13.0)
    assert q.given_up(b, since=11.0)
    q.succeeded(b)
    assert not q.is_failed(b) and q.next_retry(0.0) is None


def test_queue_without_healing_gives_up_for_good():
    """The positive control's mode: after ``retries`` failures a block is never retried."""
    q = LoadQueue(retries=1, backoff_s=0.1, max_backoff_s=1.0, heal=False)
    b = (1, 2)
    q.failed_read(b, 0.0)
    q.push(b, (0,))
    assert len(q) == 0
    assert q.given_up(b, since=1e9)


def test_failed_blocks_wait_apart_oldest_failure_first():
    """A failed block goes before fresh work only as the one probe (``probe=True``), and
    failed blocks take turns by their last failure, not by urgency: a slowly failing server
    once kept every worker on the most urgent failed blocks."""
    q = LoadQueue(retries=1, backoff_s=0.0, max_backoff_s=0.0)
    urgent, old, fresh = (0, 0), (0, 1), (0, 2)
    q.failed_read(urgent, 5.0)
    q.failed_read(old, 3.0)
    for b, key in ((urgent, (1, 0, 0)), (old, (1, 0, 1)), (fresh, (1, 0, 2))):
        q.push(b, key)
    assert q.blocks() == {urgent, old, fresh} and len(q) == 3
    assert q.pop(10.0, lambda b: "job") == (old, "job")  # the probe: the oldest failure
    assert q.pop(10.0, lambda b: "job", probe=False) == (fresh, "job")  # fresh work first
    assert q.pop(10.0, lambda b: "job", probe=False) == (urgent, "job")  # then failed ones
    assert len(q) == 0
    # a block queued fresh that failed meanwhile moves to the failed ones when popped
    q.push(fresh, (1, 0, 2))
    q.push((0, 3), (1, 0, 3))
    q.failed_read(fresh, 11.0)
    assert q.pop(12.0, lambda b: "job", probe=False) == ((0, 3), "job")
    assert q.blocks() == {fresh} and q.queued_key(fresh) == (1, 0, 2)
    # a rebuild sorts blocks into the two classes as well; cancelled counts blocks dropped
    q.rebuild([((1, 0, 0), urgent), ((1, 0, 5), (0, 4)), ((1, 0, 1), fresh)])
    assert q.cancelled == 0 and len(q) == 3
    assert q.pop(12.0, lambda b: "job", probe=False) == ((0, 4), "job")
    assert q.pop(12.0, lambda b: "job") == (urgent, "job")  # failed at 5.0, fresh at 11.0
    q.rebuild([])
    assert q.cancelled == 1 and len(q) == 0
    # turns within a class: a pinned (visible) failed block before a prefetched one that
    # failed earlier; the loader's key starts (errors read, not pinned)
    q.push(old, (1, 1, 0))  # prefetch, failed at 3.0
    q.push(fresh, (1, 0, 9))  # pinned, failed at 11.0
    assert q.pop(12.0, lambda b: "job") == (fresh, "job")
    assert q.pop(12.0, lambda b: "job") == (old, "job")


def test_quadtree_geometry_known_answers():
    grid = BlockGrid(height=9, width=17, k=3, x0=100.0, y0=200.0, dx=2.0, dy=1.0)
    cx, cy = node_centres(grid, np.array([0]), np.array([1]), 0, np.array([0]), np.array([0]))
    assert (cx[0], cy[0]) == (100.0 + 8 * 2.0 + 4 * 2.0, 200.0 - 4 * 1.0)
    cx, cy = node_centres(grid, np.array([0]), np.array([0]), 2, np.array([3]), np.array([1]))
    assert (cx[0], cy[0]) == (100.0 + 1.5 * 2 * 2.0, 200.0 - 3.5 * 2 * 1.0)
    assert half_diagonal(grid, 0) == pytest.approx(0.5 * 8 * np.hypot(2.0, 1.0))
    owner, r, c = split_children(
        np.array([7, 9]), np.array([1, 0]), np.array([2, 0]), np.array([True, False])
    )
    assert owner.tolist() == [7] * 4 and r.tolist() == [2, 2, 3, 3] and c.tolist() == [4, 5, 4, 5]
    zr = block_zranges(np.array([[1.0, np.nan]]), np.array([[5.0, np.nan]]))
    assert zr.tolist() == [[[1.0, 5.0], [1.0, 5.0]]]  # no terrain: the whole store's range


def test_set_tau_changes_what_is_streamed(tmp_path):
    from demtools import fractal, write_dem

    from streamer.paths import default_flythrough
    from streamer.session import open_session
    from tiler.tile import TileOptions, tile

    src = write_dem(tmp_path / "d.tif", fractal((257, 321), 3), cell=10.0)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, executor="threads"))
    z0, z1 = store.meta.extra["value_range"]
    cam = default_flythrough(store.grid, z0, z1, 1, 60.0, viewport=(320, 240))[0]
    with open_session(store, budget_mb=16, workers=2, tau=8.0) as s:
        coarse = s.update(cam, wait=True)
        s.set_tau(0.25)
        assert s.config.tau == 0.25 and s.planner.config.tau == 0.25
        fine = s.update(cam, wait=True)
        with pytest.raises(StreamerError, match="invalid tau"):
            s.set_tau(-1.0)
    need = {b: n for b, (_, n) in coarse.blocks.items()}
    assert any(fine.blocks[b][1] > need[b] for b in need)
    assert all(have >= n for have, n in fine.blocks.values())  # and it was loaded


def _poses():
    """The level tests' cameras and a sweep of headings, heights and offsets over GRID."""
    from streamer.camera import Camera

    out = list(CAMERAS)
    for i, yaw in enumerate(range(0, 360, 23)):
        x, y = 100.0 + 37.0 * i, 900.0 - 41.0 * i
        out.append(Camera((x, y, 20.0 + 40 * (i % 4)), yaw=yaw, pitch=-10 - i % 3 * 20, far=900))
    out.append(Camera((-400.0, 1400.0, 50.0), yaw=135, pitch=-15, far=3000))  # from outside
    return out


@pytest.mark.parametrize("culling", ["qiu", "hull"])
def test_compiled_planning_equals_the_numpy_reference(monkeypatch, culling):
    pytest.importorskip("numba")
    pl, _ = planner(SessionConfig(patch_log2=P, tau=2.0, culling=culling))
    pl.exists[3, 5] = pl.exists[6, 2] = False  # holes inside the view
    seen = 0
    for cam in _poses():
        monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
        ref = (pl.visible(cam), pl.needed(cam), pl.prefetch(cam, np.array([3.0, 1.0, 0]), set()))
        monkeypatch.setenv("TERRASTREAM_KERNELS", "numba")
        got = (pl.visible(cam), pl.needed(cam), pl.prefetch(cam, np.array([3.0, 1.0, 0]), set()))
        assert got == ref  # same blocks in the same order, same levels and screen errors
        seen += len(ref[0])
    assert seen > 100


def test_compiled_planning_positive_control(monkeypatch):
    """A block test whose polygon is one ulp lower is caught: the comparison is exact on a
    polygon whose apex is a block corner (the blocks above touch it only there)."""
    pytest.importorskip("numba")
    from streamer import levels
    from streamer import planner as planner_mod

    pl, _ = planner(SessionConfig(patch_log2=P, tau=2.0))
    tri = np.array([[192.0, 808.0], [400.0, 300.0], [100.0, 200.0]])  # (192, 808): a corner
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    ref = pl._existing(tri)
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numba")
    assert pl._existing(tri) == ref
    real = planner_mod._blocks_meeting_nb
    monkeypatch.setattr(
        planner_mod,
        "_blocks_meeting_nb",
        lambda nb, poly, *a: real(nb, np.nextafter(poly, [[np.inf, -np.inf]]), *a),
    )
    got = pl._existing(tri)
    assert levels.kernels() is not None and set(ref) - set(got) == {(0, 1)}


def test_planning_kernels_keep_the_gil():
    """The caller's short planning kernels do not release the GIL (a release hands it to a
    loader, which the caller then waits behind: see streamer/_plan_nb.py)."""
    pytest.importorskip("numba")
    from streamer import _plan_nb

    for disp in (_plan_nb.qiu_levels, _plan_nb.blocks_meeting):
        assert disp.targetoptions.get("nogil") is False, disp.__name__


def _prefetch_reference(pl: Planner, camera, velocity, visible, tau=None):
    """The prefetch plan as it was computed block by block (sets, dicts, sorted tuples)."""
    from streamer.frustum import block_edge, extension_triangle

    cfg = pl.config
    t = cfg.tau if tau is None else tau
    n = set(visible)
    poses = pl.poses(camera, velocity)
    if cfg.prefetch:
        v = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64)
        edge = block_edge(pl.grid) if cfg.extension_L is None else cfg.extension_L
        for cam in poses:
            n.update(pl._existing(extension_triangle(cam, edge, velocity=v, fps=cfg.fps)))
    blocks = sorted(n)
    wants = dict.fromkeys(blocks, (0, 0.0))
    have = pl.errors.known(blocks)
    if have:
        t_ahead = t * (cfg.plan_lookahead if cfg.prefetch else 1.0)
        levels, rho = np.zeros(len(have), dtype=np.int64), np.zeros(len(have))
        ids = np.asarray(have, dtype=np.int64).reshape(-1, 2)
        zr = pl.zr[ids[:, 0], ids[:, 1]]
        for cam in poses:
            lv, r = pl.errors.needed_levels(pl.grid, have, cam, t_ahead, cfg.metric, zr)
            np.maximum(levels, lv, out=levels)
            np.maximum(rho, r, out=rho)
        for b, lv, r in zip(have, levels.tolist(), rho.tolist(), strict=True):
            wants[b] = (lv, r)
        joined = _join(pl, {b: w[0] for b, w in wants.items()})
        wants = {b: (joined[b], w[1]) for b, w in wants.items()}
    return wants, len(n) - len(visible)


@pytest.mark.parametrize("known", [1.0, 0.6, 0.0])
@pytest.mark.parametrize("scheme", ["ours", "qiu"])
@pytest.mark.parametrize("prefetch", [True, False])
def test_prefetch_on_arrays_equals_the_block_by_block_plan(known, scheme, prefetch):
    pl, table = planner(SessionConfig(patch_log2=P, tau=2.0, scheme=scheme, prefetch=prefetch))
    rng = np.random.default_rng(int(known * 10))
    for b in [(r, c) for r in range(8) for c in range(8)]:
        if rng.random() >= known:
            table.remove(b)
    for cam in CAMERAS:
        for velocity in (None, np.array([40.0, -10.0, 0.0])):
            visible = pl.needed(cam).keys()
            plan = pl.prefetch(cam, velocity, visible)
            wants, ring = _prefetch_reference(pl, cam, velocity, visible)
            assert plan.wants == wants and list(plan.wants) == list(wants)
            assert plan.ring == ring
            assert (
                pl.prefetch(cam, velocity, set()).wants
                == _prefetch_reference(pl, cam, velocity, set())[0]
            )


def test_prefetch_comparison_control_a_plan_without_the_pose_ahead_differs():
    """The control: a planner that forgets the pose ahead plans other blocks or levels."""
    pl, _ = planner(SessionConfig(patch_log2=P, tau=2.0))
    differ = 0
    for cam in CAMERAS:
        v = np.array([400.0, -100.0, 0.0])
        visible = pl.needed(cam).keys()
        wants, _ = _prefetch_reference(pl, cam, v, visible)
        differ += pl.prefetch(cam, None, visible).wants != wants
    assert differ >= 1


@pytest.mark.parametrize(("lo", "hi"), [(0, 8), (-3, 12)])
def test_union_sorted_is_sorted_set_of_the_tuples(lo, hi):
    from streamer.planner import _ids_of, _union_sorted

    rng = np.random.default_rng(abs(lo))
    for n in (0, 1, 5, 200):
        ids = rng.integers(lo, hi, size=(n, 2))
        got = _union_sorted(ids, 8)
        want = sorted(set(map(tuple, ids.tolist())))
        assert list(map(tuple, got.tolist())) == want
        assert _ids_of(want).tolist() == [list(b) for b in want]


def test_a_waiter_leaves_blocks_that_gave_up_since_it_began_untried():
    """While ``waiting_since`` is set, a failed block that failed ``retries`` times since then
    stays queued untried (the probe goes to one that has not), and is retried once the wait
    ends; the control: a block that gave up only before the wait began is still retried."""
    q = LoadQueue(retries=2, backoff_s=0.0, max_backoff_s=0.0)
    gone, before, fresh = (0, 0), (0, 1), (0, 2)
    for t in (5.0, 6.0):
        q.failed_read(gone, t)  # gave up within the wait (it began at 4.0)
    for t in (1.0, 2.0):
        q.failed_read(before, t)  # gave up before it: a fresh round is due
    for b, key in ((gone, (1, 0, 0)), (before, (1, 0, 1)), (fresh, (1, 0, 2))):
        q.push(b, key)
    q.waiting_since = 4.0
    assert q.pop(10.0, lambda b: "job") == (before, "job")  # the probe skips `gone`
    assert q.pop(10.0, lambda b: "job") == (fresh, "job")
    assert q.pop(10.0, lambda b: "job") is None and q.blocks() == {gone}  # kept, untried
    q.waiting_since = None
    assert q.pop(10.0, lambda b: "job") == (gone, "job")  # healing resumes after the wait
