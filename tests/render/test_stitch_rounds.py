"""The incremental stitching rounds (:mod:`render.stitch_rounds`) give exactly the patches of
the reference that redoes every edge's neighbour and snapped-edge check each round
(``stitch(incremental=False)``), on multi-block synthetic terrain with node boxes and the
snapped-edge check (``conservative-view``, some blocks held coarser) and without (``qiu``);
positive controls: a cache that never redoes a check, and a neighbour update that forgets the
edges of split leaves, both differ."""

from __future__ import annotations

import numpy as np
import pytest
from stitch_scene import BLOCKS, FIELDS, GRID, RES, K, build, cameras

from render import stitch_rounds
from render.node_boxes import NodeBoxes
from render.select import _neighbours, _split, select_patches, stitch

P = 1


@pytest.fixture(scope="module")
def scene():
    return build(P)


def _pairs(scene, metric: str, taus=(0.5, 1.0, 2.0)):
    table, boxes, zr = scene
    kw = {"resident": RES, "zranges": zr, "boxes": boxes}
    for cam in cameras():
        for tau in taus:
            p = select_patches(GRID, BLOCKS, table, cam, tau, metric, None, **kw)
            # the numpy rounds (a warmed-up ``auto`` would take the compiled ones,
            # tests/render/test_stitch_fast.py)
            skw = dict(kw, tau=tau if metric == "conservative-view" else None, kernels="numpy")
            a = stitch(p, GRID, table, cam, metric, incremental=False, **skw)
            b = stitch(p, GRID, table, cam, metric, incremental=True, **skw)
            yield a, b


def _differ(a, b) -> bool:
    same = all(np.array_equal(getattr(a, f), getattr(b, f)) for f in FIELDS)
    return not (same and (a.clamped, a.violations) == (b.clamped, b.violations))


@pytest.mark.parametrize("metric", ["conservative-view", "qiu"])
def test_incremental_rounds_equal_the_reference(scene, metric):
    pairs = list(_pairs(scene, metric))
    assert sum(_differ(a, b) for a, b in pairs) == 0
    assert sum(len(a) for a, _ in pairs) > 2000  # the views select something
    assert sum(int((a.snap > 0).sum()) for a, _ in pairs) > 500  # and snap many edges


def test_positive_control_a_stale_check_differs(scene, monkeypatch):
    real = stitch_rounds.OverCache.over_edges

    def stale(self, cur, snap, check):  # checks new leaves only, not changed snaps
        self.snap = np.where(self.known[:, None], snap, self.snap)
        return real(self, cur, snap, check)

    monkeypatch.setattr(stitch_rounds.OverCache, "over_edges", stale)
    assert sum(_differ(a, b) for a, b in _pairs(scene, "conservative-view")) > 0


def test_positive_control_forgotten_neighbours_differ(scene, monkeypatch):
    real = stitch_rounds.renumber

    def forget(nbr, keep):  # never probe the edges of split neighbours again (they keep -1)
        kept, stale = real(nbr, keep)
        return kept, np.zeros_like(stale)

    monkeypatch.setattr(stitch_rounds, "renumber", forget)
    assert sum(_differ(a, b) for a, b in _pairs(scene, "qiu", taus=(0.5,))) > 0


def test_neighbours_after_split_equal_a_fresh_search(scene):
    table, boxes, zr = scene
    cam = cameras()[0]
    cur = select_patches(GRID, BLOCKS, table, cam, 4.0, "qiu", None, resident=RES, zranges=zr)
    slots = table.slots(cur.blocks)
    rng = np.random.default_rng(2)
    nbr = _neighbours(cur, K)
    res = np.array(RES)
    for _ in range(6):
        ok = np.flatnonzero(cur.depth + P < np.minimum(K, res[cur.block]))
        victims = np.unique(rng.choice(ok, size=min(len(ok), 7), replace=False))
        keep = np.ones(len(cur), bool)
        keep[victims] = False
        cur = _split(cur, victims, GRID, table, slots, cam, "qiu", res, zr)
        nbr = stitch_rounds.neighbours_after_split(cur, nbr, keep)
        assert np.array_equal(nbr, _neighbours(cur, K))
    assert (nbr >= 0).sum() > 100


def _slices(boxes: NodeBoxes, blocks, depth, row, col, level):
    """The per-patch slices :meth:`NodeBoxes.vertex_heights` and ``cell_bounds`` gather."""
    vh, cb = [], []
    for b, d, r, c, lv in zip(map(tuple, blocks.tolist()), depth, row, col, level, strict=True):
        g, rr = boxes._grid[b], boxes._level[b]
        span, step = 1 << (rr - d), 1 << (rr - lv)
        vh.append(g[r * span : (r + 1) * span + 1 : step, c * span : (c + 1) * span + 1 : step])
        n = 1 << (lv - d)
        if lv >= K:
            cb.append(np.zeros((n, n)))
            continue
        f = boxes._bound[b][lv]
        rep = (1 << lv) // f.shape[0]
        cb.append(f[np.ix_((r * n + np.arange(n)) // rep, (c * n + np.arange(n)) // rep)])
    return np.array(vh), np.array(cb, dtype=np.float64)


@pytest.mark.parametrize("cells", [0, 1, 2])
def test_batched_gathers_equal_per_patch_slices(scene, cells):
    _, boxes, _ = scene
    rng = np.random.default_rng(cells)
    res = np.array(RES)
    pick = rng.integers(0, len(BLOCKS), 200)
    level = rng.integers(cells, res[pick] + 1)
    depth = level - cells
    row, col = rng.integers(0, 1 << depth), rng.integers(0, 1 << depth)
    blocks = np.array(BLOCKS)[pick]
    want_h, want_b = _slices(boxes, blocks, depth, row, col, level)
    assert np.array_equal(boxes.vertex_heights(blocks, depth, row, col, level), want_h)
    assert np.array_equal(boxes.cell_bounds(blocks, depth, row, col, level), want_b)
    assert (want_b > 0).any() or cells == 0  # bounds gathered, not only zeros
    assert len(np.unique(level)) > 1  # several levels per call
