"""``geometry-splitting`` (Lee & Shin): the quadtree texture, the split flag, the GPU expansion
against its CPU twin, triangle splitting at T-vertices, resident caps and pages, on headless EGL."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.gpu import HeightPool
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.geometry_splitting import (
    projected_error,
    quad_errors,
    stored_tree,
)
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15
K = 5  # 33-sample blocks


def _strategy(path, size=SIZE, page_floats: int | None = None, levels=None):
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=size, patch_log2=2), ctx=CTX)
    if page_floats is not None:
        r.pool.close()
        r.pool = HeightPool(CTX, s.k, max_page_floats=page_floats)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k if levels is None else levels[b]))
    return get_strategy("geometry-splitting", r)


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


@pytest.fixture(scope="module")
def st(rough_store):
    return _strategy(rough_store)


def _nadir(x, y, h, yaw=0.0, size=SIZE) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=size, near=5.0, far=5e4)


OBLIQUE = Camera.look_at(
    (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
)


def test_the_texture_follows_the_resident_level(rough_store):
    st = _strategy(rough_store, levels={b: 3 for b in open_store(rough_store).blocks()})
    b = (1, 1)
    store = st.r.store
    want = stored_tree(store.read_errors(b)["bound"], store.read_block(b, max_level=3))
    got = st.tree(b)
    for x, y in zip(
        got.zmin + got.zmax + got.sigma, want.zmin + want.zmax + want.sigma, strict=True
    ):
        np.testing.assert_array_equal(x, y)
    sel3, _ = st.select(OBLIQUE, 0.5)
    assert st.leaf_nodes(sel3)[:, 1].max() <= 3
    for bb in store.blocks():  # the finer levels arrive: the texture is rebuilt for level 5
        st.r.upload(bb, store.read_levels(bb, 5))
    sel5, _ = st.select(OBLIQUE, 0.5)
    assert st._tex.level[b] == 5 and st.leaf_nodes(sel5)[:, 1].max() > 3
    full = store.read_block(b)
    want = stored_tree(store.read_errors(b)["bound"], full, quad_errors(full, None, range(2, 5)))
    np.testing.assert_array_equal(st.tree(b).sigma[4], want.sigma[4])
    counts, leaves, _ = st.expand_reference(OBLIQUE, 0.5)
    assert sel5.pass_counts == counts


def test_split_flag_known_cases(rough_store, tmp_path):
    (tmp_path / "one").mkdir()
    (tmp_path / "flat").mkdir()
    one = tile_dem(tmp_path / "one", rough(33, 4), 33)
    flat = tile_dem(tmp_path / "flat", np.full((33, 33), 100, np.int16), 33)
    s1, sf = _strategy(one), _strategy(flat)
    centre = (X0 + 480, Y0 - 480)
    # eye inside the root's sphere (radius >= 679 m), σ != 0: split at any τ; σ = 0: no split
    # even at τ = 0
    z1 = 0.5 * float(s1.tree((0, 0)).zmin[0][0, 0] + s1.tree((0, 0)).zmax[0][0, 0])
    assert s1.select(_nadir(*centre, z1 + 300.0), 1e9)[0].pass_counts[0] == 4
    assert sf.select(_nadir(*centre, 400.0), 0.0)[0].pass_counts[0] == 1
    assert sf.select(_nadir(*centre, 900.0), 0.0)[0].pass_counts[0] == 4  # outside: τ <= 0
    # eye outside: split iff τ <= max σ̄ (the CPU's five-point projection, Eq. 1)
    far = Camera.look_at((X0 + 480, Y0 - 4000, 1500.0), (*centre, 800.0), viewport=SIZE, near=5.0)
    tree = s1.tree((0, 0))
    zmid = 0.5 * (float(tree.zmin[0][0, 0]) + float(tree.zmax[0][0, 0]))
    rel = np.array([[centre[0], centre[1], zmid]]) - far.eye
    rho = projected_error(rel, float(tree.sigma[0][0, 0]), 32, far, 30.0, 30.0)[0]
    assert np.linalg.norm(rel) > 679 + 0.5 * float(tree.zmax[0][0, 0] - tree.zmin[0][0, 0])
    assert 1.0 < rho < 1e4
    assert s1.select(far, rho * 1.001)[0].pass_counts[0] == 1
    assert s1.select(far, rho * 0.999)[0].pass_counts[0] == 4
    # a flat block outside: σ̄ = 0, split only at τ = 0
    assert sf.select(far, 0.01)[0].pass_counts == [1] * K
    assert sf.select(far, 0.0)[0].pass_counts[0] == 4


@pytest.mark.parametrize("tau", [0.5, 2.0, 8.0])
def test_expansion_passes_match_the_cpu_twin(rough_store, tau):
    caps = {b: 3 + (b[0] + 2 * b[1]) % 3 for b in open_store(rough_store).blocks()}
    st = _strategy(rough_store)
    for cam, res in ((OBLIQUE, None), (OBLIQUE, caps), (_nadir(X0 + 1500, Y0 - 2100, 700.0), None)):
        sel, _ = st.select(cam, tau, resident=res)
        counts, leaves, _ = st.expand_reference(cam, tau, res)
        assert sel.pass_counts == counts and len(counts) == K
        got = st.leaf_nodes(sel)
        np.testing.assert_array_equal(got[np.lexsort(got.T[::-1])], leaves)
        assert len(np.unique(leaves[:, 1])) > 1 or cam is not OBLIQUE
        if res is not None:
            blk = np.array(sel.blocks)
            assert (leaves[:, 1] <= np.array([caps[tuple(b)] for b in blk[leaves[:, 0]]])).all()
            assert sel.clamped > 0


def _corners(st, blocks, nodes):
    k = st.k
    blk = np.array(blocks)[nodes[:, 0]]
    size = np.left_shift(1, k - nodes[:, 1])
    return (blk[:, 1] << k) + nodes[:, 3] * size, (blk[:, 0] << k) + nodes[:, 2] * size, size


def _expected_triangles(st, sel) -> np.ndarray:
    """From the CPU twin's split nodes: a leaf's T-vertices are the edge midpoints of split
    nodes strictly inside its edges; 2 triangles without, else 4 + their number."""
    _, _, split = st.expand_reference(sel.camera, sel.tau, _resident(sel))
    x, y, s = _corners(st, sel.blocks, split)
    h = s // 2
    mids = set()
    for mx, my in ((x + h, y), (x + s, y + h), (x + h, y + s), (x, y + h)):
        mids |= set(zip(mx.tolist(), my.tolist(), strict=True))
    x0, y0, size = _corners(st, sel.blocks, st.leaf_nodes(sel))
    out = np.zeros(len(x0), np.int64)
    for i, (x, y, s) in enumerate(zip(x0.tolist(), y0.tolist(), size.tolist(), strict=True)):
        t = 0
        for j in range(1, s):
            t += sum(p in mids for p in ((x + j, y), (x + j, y + s), (x, y + j), (x + s, y + j)))
        out[i] = 2 if t == 0 else 4 + t
    return out


def _resident(sel) -> dict:
    return {b: int(sel.table[i, 3]) for i, b in enumerate(sel.blocks)}


def _per_leaf(st, sel) -> np.ndarray:
    """Triangle records per leaf, in ``leaf_nodes`` order."""
    leaves, rec = st.leaf_nodes(sel), st.triangle_records(sel)
    key = lambda a: a[:, 0] * 10**9 + a[:, 1] * 10**8 + a[:, 2] * 10**4 + a[:, 3]  # noqa: E731
    lk, inv = np.unique(key(leaves), return_inverse=True)
    return np.bincount(np.searchsorted(lk, key(rec[:, :4])), minlength=len(lk))[inv]


def test_triangle_splitting_adds_one_triangle_per_t_vertex(rough_store):
    caps = {b: 2 + (b[0] + b[1]) % 4 for b in open_store(rough_store).blocks()}
    st = _strategy(rough_store)
    for tau, res in ((2.0, None), (1.0, caps)):
        sel, _ = st.select(OBLIQUE, tau, resident=res)
        stats = st.draw(OBLIQUE, sel)
        rec = st.triangle_records(sel)
        assert len(rec) == stats.triangles == sel.triangles
        want = _expected_triangles(st, sel)
        np.testing.assert_array_equal(_per_leaf(st, sel), want)
        assert (want == 2).any() and (want == 5).any() and (want > 5).any()
        assert len(sel.split_counts) >= 2  # at least one triangle-splitting pass did work
        # every fan triangle's segment is on the leaf's edge, at most as deep as the tree
        fan = rec[rec[:, 4] < 4]
        assert (fan[:, 6] >= fan[:, 1]).all() and (fan[:, 6] <= st.k).all()
        tri, h = st.triangles(OBLIQUE, sel)
        assert len(tri) == stats.triangles
        if res is None:  # every corner is a stored sample, fetched as stored
            full = np.zeros((129, 129))
            for b in st.r.store.blocks():
                full[b[0] * 32 : b[0] * 32 + 33, b[1] * 32 : b[1] * 32 + 33] = (
                    st.r.store.read_block(b)
                )
            np.testing.assert_array_equal(h, full[tri[..., 1], tri[..., 0]])


@pytest.mark.parametrize("tau", [0.5, 1.0, 2.0, 4.0, 8.0])
def test_no_cracks_with_mixed_resident_levels_on_several_pages(rough_store, tau):
    s = open_store(rough_store)
    levels = {b: 2 + (3 * b[0] + b[1]) % 4 for b in s.blocks()}
    # pages of 1100 floats: one level-5 block per page, so neighbours sit on different pages
    st = _strategy(rough_store, page_floats=1100, levels=levels)
    assert len(st.r.pool.pages) > 4
    cx, cy = X0 + 1920, Y0 - 1920
    ref, _ = st.r.select(_nadir(cx, cy, 1300.0), 0.0, full=True)
    st.r.draw(_nadir(cx, cy, 1300.0), ref, clear=CLEAR)
    fp = ~measure.is_clear(st.r.image(), CLEAR)
    for sel_cam in (OBLIQUE, _nadir(cx, cy, 900.0), _nadir(cx + 300, cy - 200, 1500.0, 30.0)):
        sel, _ = st.select(sel_cam, tau)
        st.draw(_nadir(cx, cy, 1300.0), sel, clear=CLEAR)
        assert measure.crack_pixels(st.r.image(), fp, CLEAR) == 0
        assert (st.leaf_nodes(sel)[:, 1] <= st.k).all()
    # the same selection without pages or caps in the way splits deeper somewhere
    free = _strategy(rough_store)
    a = st.select(OBLIQUE, tau)[0].triangles
    assert free.select(OBLIQUE, tau)[0].triangles > a


def test_tau_zero_is_the_full_mesh_in_view_and_huge_tau_the_roots(st):
    whole = _nadir(X0 + 1920, Y0 - 1920, 9000.0)
    sel, _ = st.select(whole, 0.0)
    stats = st.draw(whole, sel)
    assert (st.leaf_nodes(sel)[:, 1] == st.k).all()
    assert stats.triangles == 16 * 2 * 32 * 32 and stats.min_level == stats.max_level == st.k
    part, _ = st.select(OBLIQUE, 0.0)
    leaves = st.leaf_nodes(part)
    assert (leaves[:, 1] == st.k).all() and part.triangles == 2 * len(leaves)
    assert 0 < len(leaves) < 16 * 32 * 32  # culled: only the cells in view
    coarse, _ = st.select(whole, 1e9)
    stats = st.draw(whole, coarse)
    assert (st.leaf_nodes(coarse)[:, 1] == 0).all()
    assert stats.triangles == 16 * 2 and coarse.pass_counts == [16] * K


def test_wireframe_and_lod_colour_draw(st):
    sel, _ = st.select(OBLIQUE, 2.0)
    st.draw(OBLIQUE, sel)
    plain = st.r.image()
    st.draw(OBLIQUE, sel, wireframe=True)
    wire = st.r.image()
    st.draw(OBLIQUE, sel, lod_colour=True)
    assert measure.changed_share(plain, wire) > 0.01
    assert measure.changed_share(plain, st.r.image()) > 0.01


def test_edges_match_without_the_doubling_rule(rough_store):
    """A tree that breaks Eq. 3 (σ = 0 above rough children) makes flags non-monotone: children
    of unsplit nodes want to split. The existence walk keeps every edge matched."""
    st = _strategy(rough_store)
    broken = 0
    for b in st.r.store.blocks():
        tree = st.tree(b)
        rr, cc = np.mgrid[0:4, 0:4]
        off = (rr + cc) % 2 == 1
        tree.sigma[2][off] = 0.0  # depth-2 nodes in a checkerboard never split ...
        kids = tree.sigma[3].reshape(4, 2, 4, 2).max(axis=(1, 3))
        broken += int((kids[off] > 0).sum())  # ... over children that would
    assert broken > 20
    for tau in (0.5, 1.0):
        sel, _ = st.select(OBLIQUE, tau)
        counts, leaves, _ = st.expand_reference(OBLIQUE, tau)
        assert sel.pass_counts == counts
        got = st.leaf_nodes(sel)
        unsplit = (got[:, 1] == 2) & ((got[:, 2] + got[:, 3]) % 2 == 1)
        assert unsplit.sum() > 5 and (got[:, 1] > 3).any()
        assert (_per_leaf(st, sel) == _expected_triangles(st, sel)).all()
        cx, cy = X0 + 1920, Y0 - 1920
        nad = _nadir(cx, cy, 1300.0)
        ref, _ = st.r.select(nad, 0.0, full=True)
        st.r.draw(nad, ref, clear=CLEAR)
        fp = ~measure.is_clear(st.r.image(), CLEAR)
        st.draw(nad, sel, clear=CLEAR)
        assert measure.crack_pixels(st.r.image(), fp, CLEAR) == 0
