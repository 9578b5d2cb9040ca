"""The vectorised selection (slot-array patch table, one pass per depth, one searchsorted for
all stitching probes) gives exactly the patches of the block-by-block reference it replaced."""

from __future__ import annotations

import numpy as np
import pytest
from select_reference import RefPatchTable, ref_select_patches, ref_stitch

from render.select import DiscCull, Patches, PatchTable, select_patches, stitch
from streamer.camera import Camera
from streamer.errors import LodError
from streamer.frustum import frustum_hull, polygon_meets_circles, view_triangle
from tiler.grid import BlockGrid

FIELDS = ("blocks", "block", "depth", "row", "col", "level", "delta", "rho", "snap")


def _grid() -> BlockGrid:
    # 5 x 4 blocks of 33^2 samples, the last row and column partly padding
    return BlockGrid(height=150, width=120, k=5, x0=500000.0, y0=5.0e6, dx=30.0, dy=30.0)


def _fields(grid: BlockGrid, seed: int, coarse_cap: int = 8) -> dict:
    """Random error fields per block; depths finer than ``coarse_cap`` stored coarser."""
    rng = np.random.default_rng(seed)
    out = {}
    for b in grid.blocks():
        scale = rng.uniform(0.1, 40.0)
        out[b] = [
            (rng.gamma(1.5, scale / (d + 1), (min(1 << d, coarse_cap),) * 2)).astype(np.float32)
            for d in range(grid.k)
        ]
    return out


def _tables(grid, fields, p):
    new, old = PatchTable(grid.k, p, capacity=2), RefPatchTable(grid.k, p)
    for b, f in fields.items():
        new.add(b, f)
        old.add(b, f)
    return new, old


def _cameras(grid: BlockGrid) -> list[Camera]:
    x0, y0, x1, y1 = grid.extent
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    vp = (320, 240)
    return [
        Camera.look_at((x0 - 300, y0 - 200, 900.0), (cx, cy, 0.0), viewport=vp, far=2e4),
        Camera((cx, cy, 600.0), pitch=-90.0, viewport=vp, far=2e4),
        Camera((cx + 400, cy - 900, 120.0), yaw=20.0, pitch=-8.0, viewport=vp, far=5e3),
        Camera((x1 + 500, cy, 300.0), yaw=270.0, pitch=-20.0, viewport=vp, near=2.0, far=9e3),
        # straight down over a block corner: symmetric, touching circles
        Camera((x0 + 960.0, y0 - 960.0, 2000.0), pitch=-90.0, viewport=(64, 64), far=1e4),
    ]


def _same(a: Patches, b: Patches) -> None:
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        nan = x.dtype.kind == "f"  # NaN zranges give NaN rho in both
        assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=nan), f
    assert (a.clamped, a.violations) == (b.clamped, b.violations)


def _inputs(grid: BlockGrid, seed: int):
    rng = np.random.default_rng(seed)
    blocks = grid.blocks()
    res = rng.choice([-1, 2, 3, 4, 5, 5, 5], size=len(blocks))
    zr = np.sort(rng.uniform(0, 300, (len(blocks), 2)), axis=1)
    zr[3] = np.nan  # a block without terrain statistics
    win = np.array([grid.block_window(*b) for b in blocks])
    return blocks, res, zr, win


def _always_split(delta, centre_xyz, radius, camera):
    return np.full(np.shape(delta), np.inf)


@pytest.mark.parametrize("p", [1, 2, 3])
@pytest.mark.parametrize("metric", ["qiu", "conservative", "always"])
def test_vectorised_selection_equals_the_reference(p, metric):
    g = _grid()
    fields = _fields(g, seed=p)
    new_t, old_t = _tables(g, fields, p)
    fn = _always_split if metric == "always" else metric
    blocks, res, zr, win = _inputs(g, seed=10 + p)
    n = 0
    for cam in _cameras(g):
        polys = [None, frustum_hull(cam, (0.0, 300.0)), view_triangle(cam), np.zeros((0, 2))]
        for poly in polys:
            for tau in (0.0,) if metric == "always" else (0.0, 0.5, 1.0, 4.0):
                for w in (win, None):
                    kw = {"resident": res, "zranges": zr, "windows": w}
                    a = ref_select_patches(g, blocks, old_t, cam, tau, fn, poly, **kw)
                    b = select_patches(g, blocks, new_t, cam, tau, fn, poly, **kw)
                    _same(a, b)
                    kw.pop("windows")
                    _same(
                        ref_stitch(a, g, old_t, cam, fn, **kw), stitch(b, g, new_t, cam, fn, **kw)
                    )
                    n += len(b)
    assert n > 1000  # the scenes do select something


def test_patch_table_slots_are_reused_and_grow():
    g = _grid()
    fields = _fields(g, seed=5)
    t = PatchTable(g.k, 2, capacity=1)
    blocks = g.blocks()
    for b in blocks:
        t.add(b, fields[b])
    assert len(t) == len(blocks)
    s = t.slots(np.array(blocks))
    assert sorted(s.tolist()) == list(range(len(blocks)))
    t.remove(blocks[0])
    assert blocks[0] not in t
    with pytest.raises(LodError, match="no errors"):
        t.slots([blocks[0]])
    t.add((0, 0), fields[(0, 0)])
    assert t.slots([(0, 0)])[0] == s[0]  # the freed slot
    ref = RefPatchTable(g.k, 2)
    ref.add((1, 1), fields[(1, 1)])
    for d in range(t.depths):
        got = t.delta(t.slots([(1, 1)] * 4), d, np.arange(4) % (1 << d), np.zeros(4, int))
        want = ref.delta([(1, 1)], np.zeros(4, int), d, np.arange(4) % (1 << d), np.zeros(4, int))
        assert np.array_equal(got, want)


def test_cull_matches_polygon_meets_circles():
    rng = np.random.default_rng(1)
    g = _grid()
    for cam in _cameras(g):
        for poly in (frustum_hull(cam, (0.0, 300.0)), view_triangle(cam), frustum_hull(cam)[:2]):
            cx = rng.uniform(499000, 505000, 4000)
            cy = rng.uniform(4.994e6, 5.001e6, 4000)
            for r in (1.0, 60.0, 700.0):
                meets, inside = DiscCull(poly)(cx, cy, r)
                assert np.array_equal(meets, polygon_meets_circles(poly, cx, cy, r))
                # a disc inside: every disc within it (a descendant's) meets the polygon too
                a = rng.uniform(0, 2 * np.pi, inside.sum())
                sub_x, sub_y = cx[inside] + 0.5 * r * np.cos(a), cy[inside] + 0.5 * r * np.sin(a)
                assert (meets >= inside).all()
                assert polygon_meets_circles(poly, sub_x, sub_y, 0.5 * r).all()
                assert polygon_meets_circles(poly, sub_x, sub_y, 1e-9).all()
