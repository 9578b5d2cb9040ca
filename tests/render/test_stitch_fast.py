"""The compiled stitch (:mod:`render.stitch_fast`, kernels :mod:`render._stitch_nb` and
:mod:`render._snap_nb`) gives exactly the numpy reference's patches (every array bit for bit,
the clamped and violation counts) on multi-block synthetic terrain: node boxes with the
snapped-edge check (``conservative-view``; blocks held at full resolution, which take the exact
strip error, and coarser ones, which take the bound; a masked block) and without (``qiu``).
Positive controls: faulty kernels (a lost neighbour, an unsplit victim, children in another
order, an exact strip error zeroed) each give a difference; the strip errors themselves equal the
reference's (one ulp off is caught). Also the pool the kernels read
(:class:`render.flat_pool.FlatPool`) keeps every block's values through growth and repacking."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from stitch_scene import BLOCKS, FIELDS, GRID, RES, K, build, cameras

from render import select_kernels, stitch_fast
from render.flat_pool import FlatPool
from render.select import PatchTable, select_patches, stitch
from render.snap_error import snap_exact, snap_excess

MASKED = ((1, 1), (0, 2), (2, 1))  # blocks held coarser with nodata inside (NaN heights)
NAMES = ("leaf_keys", "probe", "restrict", "over_todo", "over_victims", "split",
         "gather_heights", "gather_cells", "gather_patches", "strip_max", "exact_all")  # fmt: skip


@pytest.fixture(scope="module")
def nb():
    mod = select_kernels.resolve("numba") if select_kernels.warm_up() else None
    if mod is None or select_kernels.stitch_kernels(mod) is None:
        pytest.skip("numba is not installed")
    return select_kernels.stitch_kernels(mod)


def _scene(p: int):
    """``(p, (table, boxes, zranges))``: the shared scene with its masked blocks (fresh)."""
    return p, build(p, MASKED)


@pytest.fixture(scope="module", params=[1, 2])
def scene(request):
    return _scene(request.param)


def _diff(a, b) -> list[str]:
    out = [f for f in FIELDS if getattr(a, f).dtype != getattr(b, f).dtype]
    out += [f for f in FIELDS if not np.array_equal(getattr(a, f), getattr(b, f))]
    return out + [f for f in ("clamped", "violations") if getattr(a, f) != getattr(b, f)]


def _compare(scene, metric: str, taus=(0.5, 1.0, 2.0)) -> tuple[int, int, int]:
    """(views that differ, views, patches made by the stitch) numba against numpy."""
    p, (table, boxes, zr) = scene
    kw = {"resident": RES, "zranges": zr, "boxes": boxes}
    bad = n = grown = 0
    for cam in cameras():
        for tau in taus:
            sel = select_patches(GRID, BLOCKS, table, cam, tau, metric, None, **kw)
            skw = dict(kw, tau=tau if metric == "conservative-view" else None)
            ref = stitch(sel, GRID, table, cam, metric, kernels="numpy", **skw)
            got = stitch(sel, GRID, table, cam, metric, kernels="numba", **skw)
            bad += bool(_diff(ref, got))
            n += 1
            grown += len(ref) - len(sel)
    return bad, n, grown


def test_compiled_stitch_equals_numpy_with_boxes(nb, scene):
    bad, n, grown = _compare(scene, "conservative-view")
    assert bad == 0 and n == 24
    assert grown > 50  # the stitch did split (restriction and snapped-edge check)


def test_compiled_stitch_equals_numpy_qiu(nb, scene):
    bad, n, grown = _compare(scene, "qiu")
    assert bad == 0 and grown > 0


def test_the_check_took_every_branch(nb, scene, monkeypatch):
    """The scene reaches the masked bound and the exact strip error (what the controls need)."""
    seen = {"masked": 0, "exact": 0}
    fake = SimpleNamespace(**{n: getattr(nb, n) for n in NAMES})

    def strip_max(dm, starts, box, tj, ti, h, masked, *a):
        seen["masked"] += int(masked.sum())
        return nb.strip_max(dm, starts, box, tj, ti, h, masked, *a)

    def exact_all(*a):
        seen["exact"] += len(a[3])  # patches
        return nb.exact_all(*a)

    fake.strip_max, fake.exact_all = strip_max, exact_all
    monkeypatch.setattr(select_kernels, "stitch_kernels", lambda m: None if m is None else fake)
    _compare(scene, "conservative-view")
    assert seen["masked"] > 0 and seen["exact"] > 0, seen


def _faulty(nb, fault: str) -> SimpleNamespace:
    mod = SimpleNamespace(**{n: getattr(nb, n) for n in NAMES})
    if fault == "lonely":  # the first full neighbour search loses one leaf's neighbours

        def probe(rows, *a):
            out = nb.probe(rows, *a)
            if len(rows) > 8:
                out[np.argmax((out >= 0).all(axis=1))] = -1
            return out

        mod.probe = probe
    elif fault == "drop":  # each round's first restriction victim is not split

        def restrict(*a):
            snap, n_bad, victims = nb.restrict(*a)
            return snap, n_bad, victims[1:]

        mod.restrict = restrict
    elif fault == "swap":  # the children of a split in another order

        def split(*a):
            leaves, *rest = nb.split(*a)
            nk = len(leaves[0]) - 4 * len(a[0])
            out = []
            for v in leaves:
                v = v.copy()
                v[nk:] = v[nk:].reshape(-1, 4)[:, ::-1].ravel()
                out.append(v)
            return (tuple(out), *rest)

        mod.split = split
    elif fault == "exact0":  # the exact strip errors of the last leaf checked zeroed

        def exact_all(*a):
            out = nb.exact_all(*a)
            out[-1] = 0.0
            return out

        mod.exact_all = exact_all
    return mod


# "drop" only with 2^1 patches: with 2^2 patches at k = 5 a restriction split needs a depth-3
# leaf beside a depth-0 one, which this scene never selects (only the check splits there).
@pytest.mark.parametrize(
    ("p", "fault"),
    [(1, f) for f in ("lonely", "drop", "swap", "exact0")]
    + [(2, f) for f in ("lonely", "swap", "exact0")],
)
def test_the_comparison_catches_a_wrong_kernel(nb, monkeypatch, p, fault):
    scene = _scene(p)
    bad_mod = _faulty(nb, fault)
    monkeypatch.setattr(select_kernels, "stitch_kernels", lambda m: None if m is None else bad_mod)
    bad, _, _ = _compare(scene, "conservative-view")
    assert bad > 0


def test_strip_errors_equal_the_reference(nb, scene):
    """The check's strip errors themselves (not only the decisions they feed) are the
    reference's bits: :func:`render.stitch_fast.strip_bounds` against
    :func:`render.snap_error.snap_excess` with the cells' bound, and
    :func:`~render.stitch_fast.exact_bounds` against :func:`~render.snap_error.snap_exact`;
    positive control: one ulp off is a difference."""
    p, (table, boxes, zr) = scene
    blocks = np.array(BLOCKS, np.int64)
    ck = stitch_fast._Check(nb, blocks, GRID, cameras()[0], None, 1.0, zr, boxes, None)
    rng = np.random.default_rng(9)
    n = 400
    b = rng.integers(0, len(BLOCKS), n)
    lev = np.array(RES)[b]
    d = np.minimum(rng.integers(0, K - p + 1, n), lev - p)
    lv = np.minimum(d + p, lev)
    r, c = (rng.integers(0, 1 << 30, n) % (1 << d) for _ in range(2))
    snap = np.minimum(rng.integers(0, p + 2, (n, 4)), (lv - d)[:, None])
    snap[snap.max(axis=1) == 0, 0] = lv[snap.max(axis=1) == 0] - d[snap.max(axis=1) == 0]
    blk = blocks[b]

    def heights(s):
        return boxes.vertex_heights(blk[s], d[s], r[s], c[s], lv[s])

    def cells(s):
        return boxes.cell_bounds(blk[s], d[s], r[s], c[s], lv[s])

    got = stitch_fast.strip_bounds(nb, ck, b, d, r, c, lv, snap)
    want = snap_excess(lv - d, snap, heights, cells)
    assert np.array_equal(got, want) and (got > 0).sum() > n
    assert np.isnan(heights(np.arange(n))).any()  # masked patches among them
    assert not np.array_equal(np.nextafter(got, -np.inf), want)
    f = np.flatnonzero(lev == K)

    def windows(s):
        g = f[s]
        return boxes.full_windows(blk[g], d[g], r[g], c[g])

    got = stitch_fast.exact_bounds(nb, ck, b[f], d[f], r[f], c[f], lv[f], snap[f])
    want = snap_exact(lv[f] - d[f], K - lv[f], snap[f], windows)
    assert np.array_equal(got, want) and (got > 0).sum() > len(f)
    assert not np.array_equal(np.nextafter(got, np.inf), want)


def test_pool_keeps_values_through_growth_and_repacks():
    rng = np.random.default_rng(3)
    pool, want = FlatPool(capacity=16), {}
    for step in range(200):
        key = int(rng.integers(0, 12))
        if rng.random() < 0.2:
            pool.drop(key)
            want.pop(key, None)
            continue
        arrs = [rng.standard_normal((s, s)) for s in rng.integers(1, 9, size=3)]
        pool.put(key, arrs)
        want[key] = arrs
        for kk, a in want.items():
            got = pool.views(kk)
            assert all(np.array_equal(x, y) for x, y in zip(got, a, strict=True)), step
    assert pool.live == sum(a.size for v in want.values() for a in v)
    assert len(pool.buf) < 4 * max(pool.live, 16) + 1024  # repacked, not only grown


def test_node_boxes_views_follow_the_pool():
    """After many updates (the pool moved) every block's heights are still its grid's."""
    table, boxes, _ = build(1, MASKED)
    rng = np.random.default_rng(4)
    grids = {}
    for i in range(40):
        b = BLOCKS[i % len(BLOCKS)]
        g = rng.standard_normal((33, 33))
        boxes.update(b, K, g, [np.zeros((1 << d, 1 << d)) for d in range(K)], (g.min(), g.max()))
        grids[b] = g
    for b, g in grids.items():
        z = np.zeros(1, np.int64)
        got = boxes.vertex_heights(np.array([b]), z, z, z, np.full(1, K))
        assert np.array_equal(got[0], g)


def _gap_table(p: int, seed: int) -> PatchTable:
    """Mixed-cell widths (metres) in the masked blocks, 0 elsewhere (as ``gap_field``)."""
    rng = np.random.default_rng(seed)
    gaps = PatchTable(K, p)
    for b in BLOCKS:
        field = [np.zeros((1 << d, 1 << d), np.float32) for d in range(K)]
        if b in MASKED:
            for d in range(K):
                f = field[d]
                f[rng.random(f.shape) < 0.3] = rng.uniform(20.0, 400.0)
        gaps.add(b, field)
    return gaps


@pytest.mark.parametrize("metric", ["conservative-view", "qiu"])
def test_compiled_walk_with_the_gap_rule_equals_numpy(nb, scene, metric):
    """``select_patches`` with ``gaps`` (the nodata rule ``"gap"``) now takes the compiled walk:
    the same patches as the numpy walk; control: the gap rule does change the selection."""
    p, (table, boxes, zr) = scene
    gaps = _gap_table(p, seed=p)
    kw = {"resident": RES, "zranges": zr, "boxes": boxes}
    bad = changed = 0
    for cam in cameras():
        for tau in (0.5, 1.0, 2.0):
            ref = select_patches(GRID, BLOCKS, table, cam, tau, metric, None, gaps=gaps,
                                 kernels="numpy", **kw)  # fmt: skip
            got = select_patches(GRID, BLOCKS, table, cam, tau, metric, None, gaps=gaps,
                                 kernels="numba", **kw)  # fmt: skip
            bad += bool(_diff(ref, got))
            plain = select_patches(GRID, BLOCKS, table, cam, tau, metric, None, kernels="numba",
                                   **kw)  # fmt: skip
            changed += len(plain) != len(ref) or bool(_diff(plain, ref))
    assert bad == 0
    assert changed > 0
