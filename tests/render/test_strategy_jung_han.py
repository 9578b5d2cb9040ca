"""``jung-han`` (Jung & Han 2002): the pointer-free quadtree, δ and δ_s, triangle flags and the
both-triangles rule, height adjustment, the pruned pass against the plain bottom-up pass, and
crack-free drawing, on headless EGL."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.jung_han import (
    SE,
    JungHan,
    flag_names,
    node_index,
    parent_index,
)
from streamer.camera import Camera
from streamer.frustum import frustum_hull, polygon_meets_rects
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15


def _renderer(path, resident: dict | None = None) -> TerrainRenderer:
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k if resident is None else resident[b]))
    return r


def _strategy(path, **kw) -> JungHan:
    st = get_strategy("jung-han", _renderer(path), **kw)
    assert isinstance(st, JungHan)
    return st


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


@pytest.fixture(scope="module")
def spike_store(tmp_path_factory):
    dem = np.full((33, 33), 100, np.int16)
    dem[3, 3] = 3100  # centre of the leaf (row 1, col 1) at depth 4: never removed
    dem[4, 2] = 101  # midpoint of the leaf's parent's bottom edge: kept, then lowered
    return tile_dem(tmp_path_factory.mktemp("spike"), dem, 33)


def _nadir(x, y, h, yaw=0.0) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=SIZE, near=5.0, far=5e4)


def _oblique() -> Camera:
    return Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )


def _full(store) -> np.ndarray:
    n = store.grid.rows * store.grid.step + 1
    out = np.zeros((n, n))
    st = store.grid.step
    for b in store.blocks():
        out[b[0] * st : b[0] * st + st + 1, b[1] * st : b[1] * st + st + 1] = store.read_block(b)
    return out


def _cracks(st: JungHan, cam: Camera, sel) -> int:
    """Crack pixels of ``sel`` drawn from ``cam`` inside the full-resolution footprint."""
    st.draw(cam, sel, clear=CLEAR)
    img = st.r.image()
    ref, _ = st.r.select(cam, 0.0, full=True)
    st.r.draw(cam, ref, clear=CLEAR)
    footprint = ~measure.is_clear(st.r.image(), CLEAR)
    assert footprint.mean() > 0.01
    return measure.crack_pixels(img, footprint, CLEAR)


def _interior_points(tri: np.ndarray) -> list[tuple[int, int, int]]:
    """(triangle, col, row) of every lattice point strictly inside a triangle edge."""
    out = []
    for t in range(len(tri)):
        for j in range(3):
            a, b = tri[t, j], tri[t, (j + 1) % 3]
            d = b - a
            n = int(np.gcd(abs(d[0]), abs(d[1])))
            for i in range(1, n):
                p = a + d * i // n
                out.append((t, int(p[0]), int(p[1])))
    return out


def test_known_blocks_flags_both_triangles_rule_and_height_adjustment(spike_store):
    st = _strategy(spike_store)
    g = st.r.grid
    cam = _nadir(g.x0 + 480, g.y0 - 480, 5000.0)
    sel, ms = st.select(cam, 0.5)
    assert _cracks(st, cam, sel) == 0 and ms >= 0
    stats = st.draw(cam, sel)
    b = (0, 0)
    leaf, p3 = node_index(1, 1, 4), node_index(0, 0, 3)
    assert parent_index(leaf) == p3 and leaf & 3 == SE
    # the spike's leaf removed its 4 edge vertices, kept its centre
    assert flag_names(sel.node_flags(b, 4, int(leaf))) == {"T", "B", "L", "R"}
    # its parent: T and L merged, but B and R kept although δ_s < τ (the leaf is not collapsed:
    # only one of the two triangles sharing the vertex exists) -> the single fans BL and RT
    assert flag_names(sel.node_flags(b, 3, int(p3))) == {"T", "L", "BL", "RT"}
    for depth in (2, 1, 0):  # the NW chain up to the root: NW child not collapsed
        f = flag_names(sel.node_flags(b, depth, int(node_index(0, 0, depth))))
        assert f == {"TR", "LB", "B", "R"}, depth
    assert len(sel.nodes) == 5 and sel.jh_triangles == 5 * 4
    # the parent's kept bottom vertex (col 2, row 4) sits on the grandparent's LB edge: lowered
    # to the mean of its neighbours (col 0 and col 4: 100 m) from its 101 m; likewise (4, 2)
    assert sorted(map(tuple, sel.adjusted.tolist())) == [(2, 4), (4, 2)]
    at = (sel.tri[..., 0] == 2) & (sel.tri[..., 1] == 4)
    assert at.any() and (sel.tri_h[at] == 100.0).all()
    assert st.r.store.read_block(b)[4, 2] == 101
    # one conforming split per T-junction, and the stats count what is drawn
    assert stats.triangles == len(sel.tri) == 22 and stats.patches == 5
    assert (stats.min_level, stats.max_level) == (1, 5)


@pytest.mark.parametrize("culled_collapse", [False, True])
def test_pruned_pass_equals_the_plain_bottom_up_pass(rough_store, culled_collapse):
    fast = _strategy(rough_store, culled_collapse=culled_collapse)
    plain = JungHan(fast.r, prune=False, culled_collapse=culled_collapse)
    for cam in (_oblique(), _nadir(X0 + 1920, Y0 - 1920, 3000.0, yaw=20.0)):
        for tau in (0.3, 1.0, 4.0):
            a, _ = fast.select(cam, tau)
            b, _ = plain.select(cam, tau)
            ka = np.sort(a.tri.reshape(len(a), -1).view("i8,i8,i8,i8,i8,i8").ravel())
            kb = np.sort(b.tri.reshape(len(b), -1).view("i8,i8,i8,i8,i8,i8").ravel())
            assert len(a) > 0 and (ka == kb).all() and len(ka) == len(kb)
            np.testing.assert_array_equal(np.sort(a.flags), np.sort(b.flags))
            assert a.evaluated <= b.evaluated
        assert a.evaluated < b.evaluated  # something was pruned at τ = 4


def test_tau_zero_draws_every_leaf_in_the_hull(rough_store):
    st = _strategy(rough_store)
    cam = _oblique()
    sel, _ = st.select(cam, 0.0)
    stats = st.draw(cam, sel)
    # independently: the 2x2-cell leaves meeting the frustum hull, 8 triangles each
    g = st.r.grid
    r, c = np.meshgrid(np.arange(64), np.arange(64), indexing="ij")
    x0, y1 = g.x0 + c * 2 * g.dx, g.y0 - r * 2 * g.dy
    hull = frustum_hull(cam, st.r.terrain_zrange)
    leaves = polygon_meets_rects(hull, x0, y1 - 2 * g.dy, x0 + 2 * g.dx, y1).sum()
    assert 0 < leaves < 64 * 64 and stats.triangles == 8 * leaves == sel.jh_triangles
    assert len(sel.adjusted) == 0 and stats.min_level == stats.max_level == 5
    np.testing.assert_array_equal(sel.tri_h, _full(st.r.store)[sel.tri[..., 1], sel.tri[..., 0]])


def test_huge_tau_draws_the_coarsest_mesh(rough_store):
    st = _strategy(rough_store)
    cam = _nadir(X0 + 1920, Y0 - 1920, 9000.0)  # the whole 4 x 4 block store in view
    sel, _ = st.select(cam, 1e9)
    stats = st.draw(cam, sel)
    # every root keeps its 9 vertices minus the 4 edge ones: T, B, L, R (the paper's level 0)
    assert stats.triangles == 16 * 4 and len(sel.nodes) == 16
    assert (sel.nodes[:, 1] == 0).all() and {int(f) for f in sel.flags} == {0xF00}
    assert len(sel.adjusted) == 0 and stats.min_level == stats.max_level == 1
    full = _full(st.r.store)
    np.testing.assert_array_equal(sel.tri_h, full[sel.tri[..., 1], sel.tri[..., 0]])
    assert {(int(c) % 32, int(r) % 32) for c, r in sel.tri.reshape(-1, 2)} <= {
        (0, 0), (16, 16)
    }  # fmt: skip


@pytest.mark.parametrize("tau", [0.5, 2.0, 8.0])
def test_drawn_mesh_is_conforming_and_adjusted_onto_edges(rough_store, tau):
    st = _strategy(rough_store)
    sel, _ = st.select(_oblique(), tau)
    verts = {(int(c), int(r)) for c, r in sel.tri.reshape(-1, 2)}
    assert not [p for p in _interior_points(sel.tri) if p[1:] in verts]  # no T-junction left
    full = _full(st.r.store)
    h = full[sel.tri[..., 1], sel.tri[..., 0]]
    moved = sel.tri_h != h
    adj = {tuple(v) for v in sel.adjusted.tolist()}
    assert len(adj) > 0
    assert {(int(c), int(r)) for c, r in sel.tri[moved]} <= adj  # only adjusted vertices move
    # the paper's rule: each adjusted vertex lies at the mean of its two neighbours along its
    # edge at its own level (drawn heights; centres are never adjusted). A neighbour can be
    # undrawn (culled next to the hull's border); then the vertex is lerped on the long edge.
    drawn = {
        (int(c), int(r)): float(v)
        for (c, r), v in zip(sel.tri.reshape(-1, 2), sel.tri_h.ravel(), strict=True)
    }
    checked = 0
    for c, r in adj:
        s = 1 << min((c & -c).bit_length() - 1 if c else 5, (r & -r).bit_length() - 1 if r else 5)
        assert (c // s) % 2 + (r // s) % 2 == 1  # an edge midpoint, not a centre
        a, b = ((c - s, r), (c + s, r)) if (c // s) % 2 else ((c, r - s), (c, r + s))
        if a in drawn and b in drawn:
            assert drawn[(c, r)] == pytest.approx((drawn[a] + drawn[b]) / 2, abs=1e-9)
            checked += 1
    assert checked > len(adj) / 2
    # a vertex has one drawn height everywhere (bit-identical shared vertices)
    key = sel.tri[..., 1] * 1000 + sel.tri[..., 0]
    order = np.argsort(key, axis=None, kind="stable")
    k, hh = key.ravel()[order], sel.tri_h.ravel()[order]
    same = k[1:] == k[:-1]
    assert (hh[1:][same] == hh[:-1][same]).all()


def test_mixed_resident_levels_have_no_cracks(rough_store):
    s = open_store(rough_store)
    levels = {b: (b[0] * 3 + b[1] * 2) % 6 for b in s.blocks()}  # 0..5 side by side
    r = _renderer(rough_store, levels)
    st = get_strategy("jung-han", r)
    cx, cy = X0 + 1920, Y0 - 1920
    for tau in (0.0, 1.0, 4.0):
        for h in (1400.0, 2000.0):  # the terrain fills the view
            cam = _nadir(cx + 300, cy - 200, h, yaw=15.0)
            sel, _ = st.select(cam, tau)
            st.draw(cam, sel, clear=CLEAR)
            assert not measure.is_clear(r.image(), CLEAR).any(), (tau, h)
            verts = {(int(c), int(rr)) for c, rr in sel.tri.reshape(-1, 2)}
            assert not [p for p in _interior_points(sel.tri) if p[1:] in verts]
        obl = _oblique()
        sel, _ = st.select(obl, tau)
        assert _cracks(st, obl, sel) == 0
    sel, _ = st.select(_nadir(cx, cy, 9000.0), 0.0)
    lv = dict(zip(sel.blocks, sel.levels.tolist(), strict=True))
    assert lv == levels and sel.corner_blocks == sum(v == 0 for v in levels.values())
    assert len(sel.adjusted) > 0  # finer blocks' border vertices lowered onto coarser edges
    # resident caps below the GPU's levels select the same as a GPU holding only those
    st_full = _strategy(rough_store)
    a, _ = st_full.select(_nadir(cx, cy, 2000.0), 1.0, resident=levels)
    b, _ = st.select(_nadir(cx, cy, 2000.0), 1.0)
    assert len(a) == len(b) and a.clamped == b.clamped > 0


def test_wireframe_and_level_colours_draw(rough_store):
    st = _strategy(rough_store)
    cam = _oblique()
    sel, ms = st.select(cam, 2.0)
    plain = st.draw(cam, sel, selection_ms=ms)
    img = st.r.image()
    wire = st.draw(cam, sel, wireframe=True)
    assert wire.triangles == plain.triangles and plain.selection_ms == ms
    assert measure.changed_share(img, st.r.image()) > 0.05
    assert st.drawn_blocks(sel) <= set(st.r.store.blocks()) and len(st.drawn_blocks(sel)) > 1


def test_culled_collapse_option_drops_the_hull_border_band(rough_store):
    paper = _strategy(rough_store, culled_collapse=False)
    opt = JungHan(paper.r)  # the default
    for cam in (_oblique(), _nadir(X0 + 1000, Y0 - 1000, 3000.0)):
        for tau in (4.0, 8.0):
            a, _ = paper.select(cam, tau)
            b, _ = opt.select(cam, tau)
            assert len(b) < len(a) and _cracks(opt, cam, b) == 0
            err = opt.screen_errors(cam, b)
            assert err.size > 5000 and np.isfinite(err).all()
    whole = _nadir(X0 + 1920, Y0 - 1920, 9000.0)  # nothing culled: the same mesh
    a, _ = paper.select(whole, 2.0)
    b, _ = opt.select(whole, 2.0)
    assert len(a) == len(b) and (np.sort(a.flags) == np.sort(b.flags)).all()


def test_nodata_is_hidden_and_its_inside_simplified(tmp_path):
    dem = np.full((65, 65), 300.0, np.float32)
    dem[20:30, 20:30] = np.nan
    st = _strategy(tile_dem(tmp_path, dem, 33, nodata=np.nan))
    g = st.r.grid
    cam = _nadir(g.x0 + 32 * g.dx, g.y0 - 32 * g.dy, 2000.0)
    counts = []
    for tau in (0.0, 1.0):
        sel, _ = st.select(cam, tau)
        st.draw(cam, sel, clear=CLEAR)
        img = st.r.image()
        hole = cam.project(np.array([[g.x0 + 24.5 * g.dx, g.y0 - 24.5 * g.dy, 300.0]]))
        assert measure.is_clear(img, CLEAR)[int(hole[1][0]), int(hole[0][0])]
        terrain = img[~measure.is_clear(img, CLEAR)].astype(int)
        assert len(terrain) > 0.4 * img.shape[0] * img.shape[1]
        assert np.ptp(terrain, axis=0).max() <= 2  # flat, no spikes or walls
        hidden = np.isnan(sel.tri_h).any(axis=1)
        inner = ((sel.tri >= 21) & (sel.tri <= 28)).all(axis=(1, 2))  # wholly in the hole
        counts.append((int(hidden.sum()), int(inner.sum())))
        err = st.screen_errors(cam, sel)
        assert err.size > 1000 and err.max() < 1e-6
    # τ = 0 keeps every triangle; at τ = 1 the hole's inside (δ = 0) collapses, its rim stays
    assert counts[0][1] > 0 and counts[1][1] < counts[0][1] and counts[1][0] > 0
