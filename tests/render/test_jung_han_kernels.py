"""``jung-han``'s compiled selection against the numpy reference (no GL: the selector runs on
a stand-in for the frame services, so these run without an EGL context)."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import rough, tile_dem

from render.strategies.jung_han import JungHanSelector
from render.strategies.jung_han import kernels as jh_kernels
from streamer.camera import Camera
from tiler.errors import KernelUnavailableError
from tiler.store import open_store

SIZE = (128, 96)
FIELDS = ("tri", "tri_h", "tri_slot", "tri_level", "nodes", "flags", "adjusted")
GPU = ("v_slot", "v_level", "v_cr", "v_h", "index")
COUNTS = ("clamped", "evaluated", "jh_triangles", "corner_blocks")
TAUS = (0.0, 0.05, 0.5, 1.0, 4.0, 1e6, 1e300)  # inf is refused (check_tau): the largest finite


class Services:
    """What :class:`JungHanSelector` reads of the frame services, every block resident."""

    def __init__(self, path) -> None:
        self.store = open_store(path)
        self.grid = self.store.grid
        self.k = self.store.k
        idx = self.store.index
        self.terrain_zrange = (float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax)))
        self._masks: dict = {}

    def mask(self, block):
        """The block's validity mask (None without nodata)."""
        if block not in self._masks:
            has = bool(self.store.index.has_nodata[block])
            self._masks[block] = self.store.read_mask(block) if has else None
        return self._masks[block]

    def gpu_level(self, block) -> int:
        """Every block is resident at level k."""
        return self.k

    def block_grid(self, block, level):
        """The block's level grid (``FrameServices.block_grid`` without a session)."""
        return self.store.read_block(block, max_level=level)

    def drawable(self, resident=None):
        """``(block, level)`` sorted, as ``FrameServices.drawable``."""
        levels = resident if resident is not None else {b: self.k for b in self.store.blocks()}
        pairs = sorted((tuple(b), min(int(lv), self.k)) for b, lv in levels.items() if lv >= 0)
        return [(b, lv) for b, lv in pairs if lv >= 0]


def differences(a, b) -> list[str]:
    """Names of the selection arrays and counts that differ between ``a`` and ``b``."""
    out = []
    for f in FIELDS + GPU:
        x, y = getattr(a, f), getattr(b, f)
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=True):
            out.append(f)
    out += [c for c in COUNTS if getattr(a, c) != getattr(b, c)]
    if a.blocks != b.blocks or not np.array_equal(a.levels, b.levels):
        out.append("blocks")
    return out


def _pair(path, **kw):
    svc = Services(path)
    return JungHanSelector(svc, kernels="numpy", **kw), JungHanSelector(svc, kernels="numba", **kw)


@pytest.fixture(scope="module")
def numba_kernels():
    pytest.importorskip("numba")
    return jh_kernels.resolve("numba")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    def make(name, dem, block, **kw):
        return tile_dem(tmp_path_factory.mktemp(name), dem, block, **kw)

    n = 129
    yy, xx = np.mgrid[0:n, 0:n]
    hole = rough(n, 5).astype(np.float32)
    hole[30:70, 10:50] = np.nan  # nodata beside terrain
    return {
        "flat": make("flat", np.full((65, 65), 300, np.int16), 33),
        "plane": make("plane", (100 + 2 * xx + 3 * yy).astype(np.int16), 33),
        "rough": make("rough", rough(n, 3), 33),
        "nodata": make("nodata", hole, 33, nodata=np.nan),
    }


def _cameras(svc: Services) -> dict[str, Camera]:
    g = svc.grid
    x0, y0 = g.x0, g.y0
    w, h = g.cols * g.step * g.dx, g.rows * g.step * g.dy
    zlo, zhi = svc.terrain_zrange
    cx, cy = x0 + 0.5 * w, y0 - 0.5 * h
    return {
        "nadir": Camera((cx, cy, zhi + 2 * w), pitch=-90.0, viewport=SIZE, near=5.0, far=1e5),
        "oblique": Camera.look_at(
            (x0 + 0.15 * w, y0 - 1.1 * h, zhi + 0.4 * w), (cx, cy, zlo), viewport=SIZE, near=5.0
        ),
        "ground": Camera(
            (x0 + 0.3 * w, y0 - 0.6 * h, zhi + 2.0), yaw=40.0, pitch=-3.0, viewport=SIZE, near=0.5
        ),
        "far": Camera((cx, cy, zhi + 1e6), pitch=-90.0, viewport=SIZE, near=1e3, far=1e7),
    }


@pytest.mark.parametrize("scene", ["flat", "plane", "rough", "nodata"])
def test_compiled_selection_equals_the_numpy_reference(stores, numba_kernels, scene):
    ref, fast = _pair(stores[scene])
    drawn = 0
    for name, cam in _cameras(ref.r).items():
        for tau in TAUS:
            a, _ = ref.select(cam, tau)
            b, _ = fast.select(cam, tau)
            assert differences(a, b) == [], (scene, name, tau)
            drawn += len(a)
    assert drawn > 0


@pytest.mark.parametrize("kw", [{"prune": False}, {"culled_collapse": False}])
def test_compiled_selection_equals_the_reference_unpruned_and_literal(stores, numba_kernels, kw):
    ref, fast = _pair(stores["rough"], **kw)
    for cam in _cameras(ref.r).values():
        for tau in (0.5, 2.0):
            assert differences(ref.select(cam, tau)[0], fast.select(cam, tau)[0]) == []


def test_compiled_selection_equals_the_reference_with_mixed_levels(stores, numba_kernels):
    ref, fast = _pair(stores["rough"])
    k = ref.r.k
    res = {b: (k - 1 - (b[0] + b[1]) % 3) for b in ref.r.store.blocks()}
    res[(0, 0)] = 0  # drawn as its 2 corner triangles
    cam = _cameras(ref.r)["oblique"]
    for tau in (0.0, 1.0, 3.0):
        a, _ = ref.select(cam, tau, resident=res)
        b, _ = fast.select(cam, tau, resident=res)
        assert len(a.adjusted) or tau == 0.0
        assert differences(a, b) == []


def test_positive_control_a_perturbed_delta_changes_the_output(stores, numba_kernels):
    ref, fast = _pair(stores["rough"])
    cam = _cameras(ref.r)["nadir"]
    a, _ = ref.select(cam, 1e6)  # everything collapses to the roots' 2 triangles
    b, _ = fast.select(cam, 1e6)
    assert differences(a, b) == []
    f = fast._forest
    k = ref.r.k
    lv = int(b.levels[0])
    half = 1 << (k - 1)
    flat = half >> (k - lv)  # vertex T of the first root: row 0, col half
    f.delta[f.offsets([b.blocks[0]])[0][0] + flat] = 1e30  # its δ_s is huge: the edge is kept
    c, _ = fast.select(cam, 1e6)
    assert "flags" in differences(a, c) and "tri" in differences(a, c)


def test_backend_selection(monkeypatch):
    assert jh_kernels.resolve("numpy") is None
    with pytest.raises(KernelUnavailableError):
        jh_kernels.resolve("fortran")
    monkeypatch.setenv("TERRASTREAM_KERNELS", "numpy")
    assert jh_kernels.resolve() is None  # the environment forces the reference
    monkeypatch.setenv("TERRASTREAM_KERNELS", "auto")
    monkeypatch.setattr(jh_kernels, "_load_numba", lambda: None)  # numba not installed
    assert jh_kernels.resolve() is None
    with pytest.raises(KernelUnavailableError):
        jh_kernels.resolve("numba")


def test_radix_sort_and_unique_equal_numpy(numba_kernels):
    rng = np.random.default_rng(7)
    for n, top in ((0, 1), (1, 5), (50, 3), (5000, 10**10), (3000, 2**62)):
        keys = rng.integers(0, top, n, dtype=np.int64)
        order = numba_kernels.argsort_stable(keys)
        assert np.array_equal(order, np.argsort(keys, kind="stable"))  # ties in input order
        if n:
            uk, first, inv = np.unique(keys, return_index=True, return_inverse=True)
            got = numba_kernels.unique_index(keys)
            for x, y in zip((uk, first, inv.ravel()), got, strict=True):
                assert np.array_equal(x, y)


def test_unique_by_hashing_equals_numpy_with_any_workspace(numba_kernels):
    """The distinct keys found by hashing, then sorted, equal ``np.unique``'s arrays: mesh-like
    keys (each ~6 times), all distinct (the table doubles), one key, none; with no workspace,
    one too short for the table, one with room for the table but not the sort, and a large
    one holding stale values (nothing read from it before it is written)."""
    rng = np.random.default_rng(3)
    verts = rng.integers(0, 1281 * 865, 6000, dtype=np.int64)
    cases = [
        rng.choice(verts, 33_000),  # the benchmark view's shape: 33 k corners, ~6 k vertices
        rng.permutation(np.arange(40_000, dtype=np.int64) * 7919),  # all distinct
        np.full(17, 2**40, dtype=np.int64),
        np.zeros(0, dtype=np.int64),
    ]
    for keys in cases:
        n = len(keys)
        want = np.unique(keys, return_index=True, return_inverse=True)
        for size in (0, 100, 2 * n + 4 * 8192, 10 * n + 20_000):
            ws = np.full(size, 12345, np.int64)  # stale values
            got = numba_kernels.unique_index_ws(keys, ws)
            for x, y in zip((want[0], want[1], want[2].ravel()), got, strict=True):
                assert x.shape == y.shape and np.array_equal(x, y), (n, size)
    # positive control: one key changed changes the answer (the comparison can fail)
    keys = cases[0].copy()
    keys[5] = 2**50
    got = numba_kernels.unique_index_ws(keys, np.empty(0, np.int64))
    assert not np.array_equal(got[0], np.unique(cases[0]))


def test_first_corner_pairs_equal_numpy(numba_kernels):
    """The GPU vertices' distinct (group, vertex) pairs found along per-vertex chains equal
    ``np.unique`` of the corner keys put in the order of their first corners: first corners,
    inverse."""
    rng = np.random.default_rng(11)
    cases = [(0, 1, 1), (1, 1, 1), (40, 3, 7), (5000, 40, 900), (3000, 2000, 50)]
    for m, groups, nv in cases:
        grp = rng.integers(0, groups, m, dtype=np.int64) * 16 + rng.integers(0, 16, m)
        tid = rng.integers(0, nv, (m, 3), dtype=np.int64)
        key = (grp[:, None] * max(nv, 1) + tid).ravel()
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
        order = np.argsort(first)
        want = (first[order], np.argsort(order)[inv.ravel()])
        got = numba_kernels.first_corner_pairs(grp, tid, nv)
        for x, y in zip(want, got, strict=True):
            assert np.array_equal(x, y)
        if m > 1:  # each pair's corners share its key, and distinct pairs differ
            assert np.array_equal(key[got[0]][got[1]], key)
            assert len(np.unique(key[got[0]])) == len(got[0])
    # positive control: the first triangle made a copy of the second shares its pairs
    tid2, grp2 = tid.copy(), grp.copy()
    tid2[0], grp2[0] = tid[1], grp[1]
    moved = numba_kernels.first_corner_pairs(grp2, tid2, nv)[1]
    assert np.array_equal(moved[:3], moved[3:6]) and not np.array_equal(moved, got[1])


def test_quick_bounds_bracket_the_exact_one(numba_kernels):
    """The traversal decides with two cheap bounds before the exact one: wherever they are
    finite, ``lo <= exact <= hi`` (then pruning, and every output, is unchanged). Boxes and
    cameras at the extremes: coordinates near 1e7 m, heights from -11 km to +9 km, FOV 1-170°,
    boxes of 0.25 m to 4 km, beside and behind the eye."""
    rng = np.random.default_rng(2)
    los, his, exact = [], [], []
    for _ in range(60):
        off = float(rng.choice([0.0, 1e4, 1e7]))
        eye = (off + rng.uniform(-5e3, 5e3), off + rng.uniform(-5e3, 5e3), rng.uniform(-11e3, 9e3))
        cam = Camera(eye, yaw=rng.uniform(0, 360), pitch=rng.uniform(-90, 30), viewport=(256, 192),
                     fov_y=rng.uniform(1, 170), near=0.1)  # fmt: skip
        basis = np.stack([cam.right, cam.up, cam.forward])
        n = 500
        size = 2.0 ** rng.integers(-2, 12, n)
        x = off + rng.uniform(-2e4, 2e4, n)
        y = off + rng.uniform(-2e4, 2e4, n)
        zlo = rng.uniform(-11e3, 9e3, n)
        zhi = zlo + rng.uniform(0, 3e3, n)
        dmax = rng.uniform(0, 50, n)
        dmax[:20] = [0.0, np.nan, np.inf, *rng.uniform(0, 1, 17)]
        lo, hi, e = numba_kernels.bounds_pair(basis, np.asarray(cam.eye, float),
                                              float(cam.focal_px), dmax, x, x + size, y, y + size,
                                              zlo, zhi)  # fmt: skip
        los.append(lo)
        his.append(hi)
        exact.append(e)
    lo, hi, e = np.concatenate(los), np.concatenate(his), np.concatenate(exact)
    finite = np.isfinite(hi)
    assert finite.mean() > 0.3  # they do bound most boxes in front of the eye
    assert np.array_equal(finite, np.isfinite(lo))
    assert np.all(hi[finite] >= e[finite])
    assert np.all(lo[finite] <= e[finite])
    # positive controls: 10 % tighter, either bound crosses the exact one somewhere
    assert np.any((hi[finite] - 1e-6) / (1.0 + 1e-6) * 0.9 < e[finite])
    assert np.any(lo[finite] / (1.0 - 1e-6) * 1.1 > e[finite])


def test_row_major_ranks_equal_the_sorted_ones(numba_kernels):
    """The assembly ranks its vertices once, knowing they are in row-major order (the sorted
    unique keys): the same four arrays as sorting both orders."""
    rng = np.random.default_rng(11)
    for n in (0, 1, 7, 4000):
        key = np.unique(rng.integers(0, 300 * 301, n, dtype=np.int64))  # row * 301 + col
        vcol, vrow = key % 301, key // 301
        want = numba_kernels.ranks(vcol, vrow)
        got = numba_kernels.ranks_sorted(vcol, vrow)
        for x, y in zip(want, got, strict=True):
            assert x.dtype == y.dtype and np.array_equal(x, y)
    # positive control: vertices out of row-major order are not ranked right that way
    p = rng.permutation(len(key))
    assert not np.array_equal(
        numba_kernels.ranks(vcol[p], vrow[p])[0], numba_kernels.ranks_sorted(vcol[p], vrow[p])[0]
    )


def _trees_equal(a, b) -> bool:
    """Every array of two ``BlockTree``s equal (values and dtypes; NaN equal to NaN)."""
    if a.level != b.level or any(len(getattr(a, f)) != a.level for f in ("dmax", "zlo", "zhi")):
        return False
    same = True
    for x, y in [(a.heights, b.heights), (a.delta, b.delta)] + [
        (p, q)
        for f in ("dmax", "zlo", "zhi")
        for p, q in zip(getattr(a, f), getattr(b, f), strict=True)
    ]:
        same &= x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)
    return bool(same)


def test_tree_build_equals_the_reference(numba_kernels):
    """The compiled per-block tree equals ``BlockTree.build`` on level grids at the extremes:
    levels 0-7, flat, constant, heights from -11 km to +9 km and near 1e7, masked samples
    (scattered, whole rows, all), infinities from partly masked neighbours."""
    from render.strategies.jung_han.kernels import build_tree
    from render.strategies.jung_han.pure import BlockTree

    rng = np.random.default_rng(8)
    grids = []
    for rr in range(0, 8):
        n = (1 << rr) + 1
        grids += [
            rng.uniform(-11000, 9000, (n, n)),
            np.full((n, n), 8848.0),
            np.zeros((n, n)),
            1e7 + rng.normal(0, 0.01, (n, n)),
            np.round(rng.normal(0, 50, (n, n))),
        ]
        g = rng.uniform(0, 100, (n, n))
        g[rng.random((n, n)) < 0.2] = np.nan
        grids.append(g)
        g = rng.uniform(0, 100, (n, n))
        g[: n // 2] = np.nan
        grids += [g, np.full((n, n), np.nan)]
    for g in grids:
        assert _trees_equal(BlockTree.build(g), build_tree(numba_kernels, g))
    with pytest.raises(ValueError, match="2\\*\\*R\\+1"):
        build_tree(numba_kernels, np.zeros((6, 6)))
    # positive control: one height moved changes the compiled tree against the reference's
    g = rng.uniform(0, 100, (65, 65))
    moved = g.copy()
    moved[32, 17] += 1e-3
    assert not _trees_equal(BlockTree.build(g), build_tree(numba_kernels, moved))


def test_forest_copies_only_the_trees_that_change(stores, numba_kernels):
    ref, fast = _pair(stores["rough"])
    cam = _cameras(ref.r)["oblique"]
    k = ref.r.k
    blocks = sorted(ref.r.store.blocks())
    fast.select(cam, 1.0)
    forest = fast._forest
    copies = forest.copies
    for part in (blocks[: len(blocks) // 2], blocks[1::2], blocks):
        res = {b: k for b in part}
        a, _ = ref.select(cam, 1.0, resident=res)
        b, _ = fast.select(cam, 1.0, resident=res)
        assert differences(a, b) == [] and fast._forest is forest
    assert forest.copies == copies  # the frame's blocks moved, no tree changed: nothing copied
    one = {b: k for b in blocks} | {blocks[0]: k - 1}
    a, _ = ref.select(cam, 1.0, resident=one)
    b, _ = fast.select(cam, 1.0, resident=one)
    assert differences(a, b) == [] and forest.copies == copies + 1  # one tree rebuilt


def test_forest_reuses_and_compacts_its_regions(stores, numba_kernels, monkeypatch):
    """Random sequences of resident levels (trees built, rebuilt at other levels and dropped):
    every frame's selection equals the numpy reference's while the forest reuses freed regions,
    grows and compacts (a small threshold forces compactions). Control: a forest that reuses a
    region without copying the new tree into it differs from the reference."""
    from render.strategies.jung_han.kernels import Forest

    monkeypatch.setattr(Forest, "MIN_COMPACT", 0)
    ref, fast = _pair(stores["rough"])
    cam = _cameras(ref.r)["oblique"]
    k = ref.r.k
    blocks = sorted(ref.r.store.blocks())
    rng = np.random.default_rng(4)

    def frames(sel):
        out = []
        for _ in range(30):
            res = {b: int(rng.integers(max(k - 3, 0), k + 1)) for b in blocks if rng.random() < 0.7}
            sel._trees = {b: t for b, t in sel._trees.items() if b in res}  # dropped trees
            out.append((res, sel.select(cam, 1.0, resident=res)[0]))
        return out

    for res, b in frames(fast):
        a, _ = ref.select(cam, 1.0, resident=res)
        assert differences(a, b) == []
    f = fast._forest
    assert f.copies > 30 and f.compactions > 0
    hmax = sum(t.heights.size for t in fast._trees.values())
    assert f._hend <= 2 * max(hmax, 1) + max(t.heights.size for t in fast._trees.values())
    # the control: regions reused without the new tree's data
    rng = np.random.default_rng(4)
    _, fast2 = _pair(stores["rough"])
    real = Forest._copy
    seen = []

    def lazy(self, t, h, p, size):
        if h < self._hend - size[0] and seen:  # a reused region: left as it was
            self.copies += 1
            return
        seen.append(1)
        real(self, t, h, p, size)

    monkeypatch.setattr(Forest, "_copy", lazy)
    bad = 0
    for res, b in frames(fast2):
        a, _ = ref.select(cam, 1.0, resident=res)
        bad += differences(a, b) != []
    assert bad > 0


def test_a_forest_grows_once_for_the_trees_it_receives_together(stores, numba_kernels, monkeypatch):
    """The first compiled selection places every resident tree at once: one growth to their
    total size (growing by doubling per tree copied the used part ~log2(n) times and touched
    twice the memory: the viewer's switch to the compiled path, 47 -> 17 ms)."""
    from render.strategies.jung_han.kernels import Forest

    grew: list[bool] = []
    real = Forest._reserve

    def spy(self, nh, npy):
        n0 = len(self.heights)
        real(self, nh, npy)
        grew.append(len(self.heights) != n0)

    monkeypatch.setattr(Forest, "_reserve", spy)
    _, fast = _pair(stores["rough"])
    fast.select(_cameras(fast.r)["oblique"], 1.0)
    assert len(fast._trees) >= 4
    assert sum(grew) == 1
    assert fast._forest._hend == sum(t.heights.size for t in fast._trees.values())


def _unsplit_mesh(stores):
    """A mixed-level frame's triangles before the conforming split, with T-junctions."""
    ref = JungHanSelector(Services(stores["rough"]), kernels="numpy")
    ref.stitching = False  # no height adjustment, no split: the paper's triangles
    k = ref.r.k
    res = {b: (k - 1 - (b[0] + b[1]) % 3) for b in ref.r.store.blocks()}
    sel, _ = ref.select(_cameras(ref.r)["oblique"], 1.0, resident=res)
    return sel.tri, sel.tri_slot, sel.tri_level


@pytest.mark.parametrize("order", ["sorted", "shuffled"])
def test_mesh_kernels_with_vertex_ids_equal_the_reference(stores, numba_kernels, order):
    from render.strategies.jung_han import pure

    tri, slot, tl = _unsplit_mesh(stores)
    key = tri[..., 1] * 100_000 + tri[..., 0]
    uk, inv = np.unique(key.ravel(), return_inverse=True)
    perm = np.arange(len(uk))  # vertex ids in key order, or any order (the kernels rank them)
    if order == "shuffled":
        perm = np.random.default_rng(3).permutation(len(uk))
    vcol, vrow = np.empty_like(uk), np.empty_like(uk)
    vcol[perm], vrow[perm] = uk % 100_000, uk // 100_000
    tid = np.ascontiguousarray(perm[inv].reshape(-1, 3))
    ids, ends, frac = pure.t_junctions(tri, vcol, vrow)
    got = numba_kernels.t_junctions(tri, tid, vcol, vrow)
    assert len(ids) > 0  # the frame has T-junctions: the comparison is not vacuous
    for x, y in zip((ids, ends, frac), got[:3], strict=True):
        assert np.array_equal(x, y)
    for end, eid in ((ends[:, 0], got[3]), (ends[:, 1], got[4])):  # the ends' vertex ids
        assert np.array_equal(np.stack([vcol[eid], vrow[eid]], -1), end)
    want = pure.conform(tri, slot, tl, vcol, vrow)
    t2, i2, s2, l2, ok = numba_kernels.conform(tri, tid, slot, tl, vcol, vrow)
    assert ok and len(t2) > len(tri)  # some triangles were split
    for x, y in zip(want, (t2, s2, l2), strict=True):
        assert np.array_equal(x, y)
    assert np.array_equal(np.stack([vcol[i2], vrow[i2]], -1), t2)  # ids follow the corners
    # positive control: corners with the ids of other vertices fail the id check
    bad = np.roll(tid, 1, axis=0)
    b2 = numba_kernels.conform(tri, bad, slot, tl, vcol, vrow)
    assert not np.array_equal(np.stack([vcol[b2[1]], vrow[b2[1]]], -1), b2[0])


def _soup(rng, m, side):
    """``m`` random triangles on a ``side``² lattice (overlapping, some degenerate, many
    axis-aligned edges) with their vertex ids: ``(tri, tid, vcol, vrow)``."""
    tri = rng.integers(0, side, (m, 3, 2), dtype=np.int64)
    flat = rng.random(m) < 0.5  # make an edge axis-aligned in half of them
    tri[flat, 1, 1] = tri[flat, 0, 1]
    tall = rng.random(m) < 0.3
    tri[tall, 2, 0] = tri[tall, 1, 0]
    key = tri[..., 1] * (side + 2) + tri[..., 0]
    uk, inv = np.unique(key.ravel(), return_inverse=True)
    vcol, vrow = uk % (side + 2), uk // (side + 2)
    return tri, np.ascontiguousarray(inv.reshape(m, 3)), vcol, vrow


def test_t_junctions_and_picks_on_triangle_soups(numba_kernels):
    """The T-junction search walks only from the starts of edges with a vertex inside; on
    triangle soups (overlapping edges on one side, degenerate triangles, edges that start
    inside others) it equals the reference's per-group searches, and the split's first-round
    choices it finds in the same pass equal the split's own."""
    from render.strategies.jung_han import pure

    rng = np.random.default_rng(21)
    found = picked = 0
    for trial in range(300):
        m, side = int(rng.integers(1, 60)), int(rng.integers(3, 24))
        tri, tid, vcol, vrow = _soup(rng, m, side)
        ids, ends, frac = pure.t_junctions(tri, vcol, vrow)
        got = numba_kernels.t_junctions(tri, tid, vcol, vrow)
        for x, y in zip((ids, ends, frac), got[:3], strict=True):
            assert np.array_equal(x, y), trial
        p1, d1, p2, d2 = numba_kernels.t_junction_picks(tri, tid, vcol, vrow)
        assert np.array_equal(p1, p2) and np.array_equal(d1[p1 >= 0], d2[p2 >= 0]), trial
        found += len(ids)
        picked += int((p1 >= 0).sum())
    assert found > 300 and picked > 300  # not vacuous


def _any_covering_edge(tri, vcol, vrow):
    """The T-junction ids by a different rule: a vertex strictly inside *any* axis-aligned edge
    of a non-degenerate triangle (the reference takes, per group, only the last edge starting
    at the nearest vertex before)."""
    p = np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])
    q = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    o = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
    hit = np.zeros(len(vcol), bool)
    for axis in (1, 0):
        other = 1 - axis
        line_v, pos_v = (vrow, vcol) if axis == 1 else (vcol, vrow)
        on = (p[:, axis] == q[:, axis]) & (np.abs(p[:, other] - q[:, other]) >= 2)
        on &= o[:, axis] != p[:, axis]
        lo = np.minimum(p[on, other], q[on, other])
        hi = np.maximum(p[on, other], q[on, other])
        inside = (p[on, axis][:, None] == line_v) & (lo[:, None] < pos_v) & (pos_v < hi[:, None])
        hit |= inside.any(0)
    return np.flatnonzero(hit)


def test_t_junction_soups_tell_the_rules_apart(numba_kernels):
    """Positive control for the soup test: on its soups a walk that took any covering edge
    (ignoring which edge starts nearest, so ignoring the takeover by a later start) would
    differ from the reference's rule, which the compiled walk matches (so the soups exercise
    that rule, which real meshes, with no overlapping edges, do not)."""
    rng = np.random.default_rng(21)
    differ = 0
    for _ in range(300):
        m, side = int(rng.integers(1, 60)), int(rng.integers(3, 24))
        tri, tid, vcol, vrow = _soup(rng, m, side)
        got = numba_kernels.t_junctions(tri, tid, vcol, vrow)[0]
        differ += not np.array_equal(_any_covering_edge(tri, vcol, vrow), got)
    assert differ > 10


def test_block_hull_tests_equal_the_reference(stores, numba_kernels):
    from render.strategies.jung_han import corners_inside
    from streamer.frustum import frustum_hull, polygon_meets_rects

    sel = JungHanSelector(Services(stores["rough"]), kernels="numba")
    g, size = sel.r.grid, 1 << sel.r.k
    rng = np.random.default_rng(5)
    r0 = rng.integers(-8, 12, 400).astype(np.int64) * (size // 4)  # around and over the terrain
    c0 = rng.integers(-8, 12, 400).astype(np.int64) * (size // 4)
    gg = (float(g.x0), float(g.y0), float(g.dx), float(g.dy))
    seen, moved_differs = set(), []
    for cam in _cameras(sel.r).values():
        poly = frustum_hull(cam, sel.r.terrain_zrange)
        box = sel._box(r0, c0, size)
        want = polygon_meets_rects(poly, *box), corners_inside(poly, *box)
        got = numba_kernels.block_hits(r0, c0, size, *sel._poly_args(poly), *gg)
        for x, y in zip(want, got, strict=True):
            assert np.array_equal(x, y)
        seen |= {(bool(m), bool(i)) for m, i in zip(*want, strict=True)}
        # positive control: the same test one block further east disagrees somewhere
        moved = numba_kernels.block_hits(r0, c0 + size, size, *sel._poly_args(poly), *gg)
        moved_differs.append(not np.array_equal(moved[0], want[0]))
    assert any(moved_differs)
    assert seen >= {(False, False), (True, False), (True, True)}  # every outcome occurs


_FIRST_USE = """
import sys
import numba
sys.path.insert(0, {here!r})
from test_jung_han_kernels import Services, _cameras
from render.strategies.jung_han import JungHanSelector
from render.strategies.jung_han import _assemble_nb, _kernels_nb, _mesh_nb, _tree_nb
from render.strategies.jung_han import kernels as jh_kernels
from render.strategies.jung_han.warm import warm_up_selection
mods = (_assemble_nb, _kernels_nb, _mesh_nb, _tree_nb)
def loaded():
    return sum(len(getattr(m, n).signatures) for m in mods for n in dir(m)
               if isinstance(getattr(m, n), numba.core.registry.CPUDispatcher))
warm = {warm}
if warm:
    jh_kernels.warm_up(warm_up_selection)
before = loaded()
svc = Services({path!r})
sel = JungHanSelector(svc, kernels="numba")
sel.select(_cameras(svc)["oblique"], 1.0)
print(warm, before, loaded())
"""


@pytest.mark.parametrize("warm", [True, False])
def test_warm_up_loads_every_kernel_a_real_selection_calls(stores, numba_kernels, warm):
    """The viewer's warm-up runs a compiled selection of a synthetic scene
    (``jung_han.warm``) so that the render thread's first compiled selection loads no kernel
    (it spent ~80 ms doing so); in a fresh process, a real selection after it adds no
    signature. Control (``warm=False``): the same selection loads its kernels itself."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = _FIRST_USE.format(here=str(Path(__file__).parent), warm=warm, path=str(stores["nodata"]))
    env = {k: v for k, v in os.environ.items() if k != "TERRASTREAM_KERNELS"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, env=env
    )
    assert out.returncode == 0, out.stderr[-3000:]
    flag, before, after = out.stdout.split()
    if warm:
        assert int(before) >= 4 and after == before
    else:
        assert before == "0" and int(after) >= 4
