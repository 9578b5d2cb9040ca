"""``seamless-patches`` (Livny, Kogan & El-Sana): cached tiles and strips, ε = ρ·l/d edge
resolutions, crack-free stitching, on headless EGL."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import cracks, measure
from render.errors import RenderError
from render.pipeline import drawn_cracks, open_render_session, tradeoff
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.step import stream_step
from render.strategies import get_strategy
from render.strategies.base import GlobalHeights
from render.strategies.seamless import (
    SeamlessPatches,
    edge_resolution,
    paper_precision,
)
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15
OBLIQUE = ((X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0))


def _strategy(path, res_log2: int = 3, caps: dict | None = None, **opts) -> SeamlessPatches:
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, (caps or {}).get(b, s.k)))
    st = get_strategy("seamless-patches", r, res_log2=res_log2, **opts)
    assert isinstance(st, SeamlessPatches) and st.name == "seamless-patches"
    return st


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


def _nadir(x, y, h, yaw=0.0) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=SIZE, near=5.0, far=5e4)


def _oblique() -> Camera:
    return Camera.look_at(*OBLIQUE, viewport=SIZE, near=5.0)


def _area2(t: np.ndarray) -> np.ndarray:
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]


def _edge_use(tri: np.ndarray) -> Counter:
    use: Counter = Counter()
    for t in tri.tolist():
        for i in range(3):
            a, b = tuple(t[i]), tuple(t[(i + 1) % 3])
            use[(a, b) if a < b else (b, a)] += 1
    return use


# -- cached meshes ---------------------------------------------------------------------------


# -- ε = ρ l / d -----------------------------------------------------------------------------


def test_selection_uses_epsilon_of_the_stored_errors(tmp_path):
    dem = rough(33, 5)
    st = _strategy(tile_dem(tmp_path, dem, 33), res_log2=5)
    g = st.r.grid
    cam = Camera.look_at(
        (g.x0 + 480, g.y0 - 1300, 900.0), (g.x0 + 480, g.y0 - 480, 800.0), viewport=SIZE,
        near=5.0,
    )  # fmt: skip
    sel, _ = st.select(cam, 6.0)
    assert len(sel) == 1 and sel.depth[0] == 0  # k = c = 5: the root patch only
    bound1 = st.r.store.read_errors((0, 0))["bound"][1].max()  # level 1: the coarsest tiles
    zmin, zmax = float(dem.min()), float(dem.max())
    for e, ((r0, c0), (r1, c1)) in enumerate(
        (((0, 0), (0, 32)), ((0, 32), (32, 32)), ((32, 0), (32, 32)), ((0, 0), (32, 0)))
    ):
        xa, ya = g.sample_xy(r0, c0)
        xb, yb = g.sample_xy(r1, c1)
        ex, ey, ez = cam.eye
        hx = max(min(xa, xb) - ex, 0.0, ex - max(xa, xb))
        hy = max(min(ya, yb) - ey, 0.0, ey - max(ya, yb))
        d = float(np.sqrt(hx * hx + hy * hy + max(ez - zmax, zmin - ez, 0.0) ** 2))
        length = float(np.hypot(xb - xa, yb - ya))
        rho = 2 * cam.focal_px * bound1 / (6.0 * 32 * length)
        assert sel.eps[0, e] == pytest.approx(rho * length / d, rel=1e-5)
        assert sel.edge_res[0, e] == edge_resolution(sel.eps[0, e], 5)
    assert len(np.unique(sel.edge_res)) > 1  # the near (south) edge is finer than the far one
    assert sel.edge_res[0, 2] > sel.edge_res[0, 0]


def test_leaves_meet_epsilon_unless_at_the_bottom(rough_store):
    st = _strategy(rough_store)
    for tau in (1.0, 2.0, 4.0):
        sel, _ = st.select(_oblique(), tau)
        bottom = sel.depth == st.r.k - st.c
        assert ((sel.eps <= 1.0).all(axis=1) | bottom).all()
        assert sel.violations == 0 and sel.clamped == 0
        # every tile is within the patch's resolutions and its block's levels
        assert ((sel.edge_res >= 1) & (sel.edge_res <= st.c)).all()
        # no edge is drawn coarser than its own ε asks (a shared edge takes the finest wish;
        # a coarse patch that cannot give it is split)
        own = sel.depth[:, None] + edge_resolution(sel.eps, st.c)
        assert (sel.edge_level >= own).all()


# -- stitching and drawing -------------------------------------------------------------------


def _edge_vertices(sel, k: int) -> list[tuple[int, tuple, set]]:
    """Per leaf edge: (leaf, ((r0, c0), (r1, c1)) global segment, its vertex set)."""
    out = []
    for i in range(len(sel)):
        d = int(sel.depth[i])
        size = 1 << (k - d)
        r0 = (int(sel.blocks[sel.block[i], 0]) << k) + int(sel.row[i]) * size
        c0 = (int(sel.blocks[sel.block[i], 1]) << k) + int(sel.col[i]) * size
        segs = (
            ((r0, c0), (r0, c0 + size)),
            ((r0, c0 + size), (r0 + size, c0 + size)),
            ((r0 + size, c0), (r0 + size, c0 + size)),
            ((r0, c0), (r0 + size, c0)),
        )
        for e, (a, b) in enumerate(segs):
            step = 1 << (k - int(sel.edge_level[i, e]))
            t = range(0, size + 1, step)
            pts = {(a[0], a[1] + x) for x in t} if a[0] == b[0] else {(a[0] + x, a[1]) for x in t}
            out.append((i, (a, b), pts))
    return out


@pytest.mark.parametrize("c", [2, 3])
def test_neighbours_shared_edges_have_identical_vertex_sets(rough_store, c):
    st = _strategy(rough_store, res_log2=c)
    k = st.r.k
    pairs = mixed_depth = mixed_level = jump = 0
    for tau in (1.0, 2.0, 4.0):
        sel, _ = st.select(_oblique(), tau)
        assert sel.violations == 0
        edges = _edge_vertices(sel, k)
        for (i, (a, b), p), (j, (a2, b2), p2) in itertools.combinations(edges, 2):
            if i == j or (a[0] == b[0]) != (a2[0] == b2[0]):
                continue
            axis = 0 if a[0] == b[0] else 1  # the fixed coordinate
            if a[axis] != a2[axis]:
                continue
            lo, hi = max(a[1 - axis], a2[1 - axis]), min(b[1 - axis], b2[1 - axis])
            if hi <= lo:
                continue
            pairs += 1
            assert {v for v in p if lo <= v[1 - axis] <= hi} == {
                v for v in p2 if lo <= v[1 - axis] <= hi
            }, (tau, i, j)
            mixed_depth += sel.depth[i] != sel.depth[j]
            jump = max(jump, abs(int(sel.depth[i]) - int(sel.depth[j])))
            lv = {e: sel.edge_level[i, e] for e in range(4)}
            mixed_level += len(set(lv.values())) > 1
    assert pairs > 100 and mixed_depth > 10 and mixed_level > 10
    assert 1 <= jump <= c - 1  # the restriction: a coarse edge is matchable by the finer side


def test_the_whole_frame_is_watertight(rough_store):
    st = _strategy(rough_store)
    k = st.r.k
    cam = _oblique()
    sel, _ = st.select(cam, 2.0)
    assert len(np.unique(sel.depth)) == 3 and len(np.unique(sel.edge_res)) == 3
    tri, h = st.triangles(cam, sel)
    assert len(tri) == st.draw(cam, sel).triangles
    assert (_area2(tri) != 0).all()
    size = np.left_shift(1, k - sel.depth)
    r0 = (sel.blocks[sel.block, 0] << k) + sel.row * size
    c0 = (sel.blocks[sel.block, 1] << k) + sel.col * size
    once = 0
    for (a, b), n in _edge_use(tri).items():
        assert n in (1, 2), (a, b, n)
        if n == 1:  # only on the outline of the drawn leaves: no crack, no T-junction
            once += 1
            x, y = (a[0] + b[0]) / 2, (a[1] + b[1]) / 2
            cover = (r0 <= y) & (y <= r0 + size) & (c0 <= x) & (x <= c0 + size)
            assert cover.sum() == 1, (a, b)
            i = int(np.argmax(cover))
            assert y in (r0[i], r0[i] + size[i]) or x in (c0[i], c0[i] + size[i]), (a, b)
    assert once > 0


def test_drawn_triangles_match_the_cpu_twin_and_the_store(rough_store):
    st = _strategy(rough_store)
    cam = _oblique()
    sel, _ = st.select(cam, 2.0)
    assert len(np.unique(sel.depth)) > 1 and len(np.unique(sel.edge_res)) > 1
    stats = st.draw(cam, sel)
    tri, h = st.triangles(cam, sel)
    assert len(tri) == stats.triangles == st.triangle_count(sel)
    cpu = st.cpu_triangles(sel)

    def canon(t):
        key = t[..., 1] * 100003 + t[..., 0]
        return np.sort(np.sort(key, axis=1), axis=0)

    np.testing.assert_array_equal(canon(cpu), canon(tri))
    np.testing.assert_array_equal(h, GlobalHeights(st.r.store)(tri[..., 1], tri[..., 0]))
    st.draw(cam, sel, wireframe=True, lod_colour=True)


@pytest.mark.parametrize("tau", [0.5, 1, 2, 4, 8])
def test_no_cracks_looking_straight_down(rough_store, tau):
    st = _strategy(rough_store)
    cx, cy = X0 + 1920, Y0 - 1920  # a corner shared by 4 blocks
    for h, yaw, dx in ((1400.0, 0.0, 0.0), (1800.0, 30.0, 250.0), (2600.0, 0.0, -400.0)):
        cam = _nadir(cx + dx, cy + dx / 2, h, yaw)
        sel, _ = st.select(cam, tau)
        st.draw(cam, sel, clear=CLEAR)
        assert not measure.is_clear(st.r.image(), CLEAR).any(), h
    obl = Camera((cx, cy - 1500, 1500.0), pitch=-60.0, viewport=SIZE, near=5.0, far=1e5)
    sel, _ = st.select(obl, tau)
    nad = _nadir(cx, cy, 1300.0)
    st.draw(nad, sel, clear=CLEAR)
    img = st.r.image()
    ref, _ = st.r.select(nad, 0.0, full=True)
    st.r.draw(nad, ref, clear=CLEAR)
    fp = ~measure.is_clear(st.r.image(), CLEAR)
    assert fp.sum() > 5000 and measure.crack_pixels(img, fp, CLEAR) == 0
    if tau >= 2:
        assert len(np.unique(sel.depth)) > 1 and len(np.unique(sel.edge_level)) > 1


def test_tau_zero_draws_the_full_mesh_and_huge_tau_the_coarsest(rough_store):
    st = _strategy(rough_store)
    cam = _nadir(X0 + 1920, Y0 - 1920, 9000.0)
    sel, _ = st.select(cam, 0.0)
    stats = st.draw(cam, sel)
    assert (sel.depth == st.r.k - st.c).all() and (sel.edge_level == st.r.k).all()
    assert stats.triangles == 16 * 2 * 32 * 32  # 2 triangles per full-resolution cell
    ref, _ = st.r.select(cam, 0.0, full=True)
    assert stats.triangles == st.r.draw(cam, ref).triangles
    sel, _ = st.select(cam, 1e9)
    stats = st.draw(cam, sel)
    assert len(sel) == 16 and (sel.depth == 0).all() and (sel.edge_res == 1).all()
    assert stats.triangles == 16 * 8 and stats.max_level == 1  # 2 x 2 cells per block


def _mkdir(tmp, name):
    (tmp / name).mkdir()
    return tmp / name


def test_known_answer_scenes(tmp_path):
    flat = _strategy(tile_dem(_mkdir(tmp_path, "f"), np.full((33, 33), 100, np.int16), 33))
    cam = _nadir(X0 + 480, Y0 - 480, 600.0)
    sel, _ = flat.select(cam, 0.0)  # δ = 0: exact at the coarsest resolution
    assert flat.draw(cam, sel).triangles == 8
    img = flat.r.image()
    assert (img == img[0, 0]).all() and not measure.is_clear(img, flat.r.config.clear).any()
    assert flat.screen_errors(cam, sel).max() < 1e-6
    dem = np.zeros((65, 65), np.int16)
    dem[30:35, 40:45] = 400
    st = _strategy(tile_dem(_mkdir(tmp_path, "p"), dem, 65))
    g = st.r.grid
    peak = np.array([g.x0 + 42 * g.dx, g.y0 - 32 * g.dy, 400.0])
    cam = Camera.look_at(
        (g.x0 + 960, g.y0 - 2600, 1500.0), (g.x0 + 960, g.y0 - 960, 0.0), viewport=SIZE,
        near=5.0, far=1e4,
    )  # fmt: skip
    sel, _ = st.select(cam, 0.5)
    st.draw(cam, sel)
    img = st.r.image().astype(int)
    px, py, _ = cam.project(peak[None])
    assert img[int(py[0]), int(px[0])].sum() > 500
    ground = cam.project(np.array([[g.x0 + 10 * g.dx, g.y0 - 32 * g.dy, 0.0]]))
    assert img[int(ground[1][0]), int(ground[0][0])].sum() < 400


def test_resident_levels_cap_the_tiles_without_cracks(rough_store):
    caps = {(r, c): (2 if (r + c) % 2 else 5) if r < 2 else 3 for r in range(4) for c in range(4)}
    st = _strategy(rough_store, caps=caps)
    cx, cy = X0 + 1920, Y0 - 1920
    cam = _nadir(cx, cy, 2600.0)
    for tau in (0.0, 1.0):
        sel, _ = st.select(cam, tau)
        cap = np.array([caps[tuple(b)] for b in sel.blocks[sel.block].tolist()])
        assert (sel.edge_level.max(axis=1) <= cap).all() and sel.violations == 0
        tri, h = st.triangles(cam, sel)  # only resident samples were fetched
        np.testing.assert_array_equal(h, GlobalHeights(st.r.store)(tri[..., 1], tri[..., 0]))
        st.draw(cam, sel, clear=CLEAR)
        assert not measure.is_clear(st.r.image(), CLEAR).any()
    assert sel.clamped > 0
    # an explicit cap below the GPU's
    sel, _ = st.select(cam, 0.0, resident={b: 1 for b in caps})
    assert (sel.edge_level == 1).all() and st.draw(cam, sel).triangles == 16 * 8


def test_nothing_in_view_draws_nothing(rough_store):
    st = _strategy(rough_store)
    # 4 km east of the store, looking east
    cam = Camera((X0 + 8000, Y0 - 1920, 1000.0), yaw=90.0, pitch=-10.0, viewport=SIZE, far=1e4)
    sel, ms = st.select(cam, 1.0)
    assert len(sel) == 0 and ms >= 0
    assert st.draw(cam, sel).triangles == 0 and st.screen_errors(cam, sel).size == 0
    assert st.surface(cam, sel)[0].size == 0 and st.drawn_blocks(sel) == set()


# -- ρ as published (rho="paper") ----------------------------------------------------------


def _edge_distances(g, cam, zmin: float, zmax: float, n: int) -> list[tuple[float, float]]:
    """(length, distance) of the root patch's edges N, E, S, W (one block of ``n`` cells)."""
    out = []
    for (r0, c0), (r1, c1) in (
        ((0, 0), (0, n)), ((0, n), (n, n)), ((n, 0), (n, n)), ((0, 0), (n, 0))
    ):  # fmt: skip
        xa, ya = g.sample_xy(r0, c0)
        xb, yb = g.sample_xy(r1, c1)
        ex, ey, ez = cam.eye
        hx = max(min(xa, xb) - ex, 0.0, ex - max(xa, xb))
        hy = max(min(ya, yb) - ey, 0.0, ey - max(ya, yb))
        d = float(np.sqrt(hx * hx + hy * hy + max(ez - zmax, zmin - ez, 0.0) ** 2))
        out.append((float(np.hypot(xb - xa, yb - ya)), d))
    return out


def test_paper_rho_refines_flat_terrain_as_published(tmp_path):
    flat = np.full((33, 33), 800, np.int16)
    path = tile_dem(tmp_path, flat, 33)
    paper = _strategy(path, res_log2=5, rho="paper")
    ours = _strategy(path, res_log2=5)
    assert paper.rho == "paper" and ours.rho == "bound"
    g = paper.r.grid
    cam = Camera.look_at(
        (g.x0 + 480, g.y0 - 1300, 900.0), (g.x0 + 480, g.y0 - 480, 800.0), viewport=SIZE,
        near=5.0,
    )  # fmt: skip
    tau = 6.0
    sel, _ = paper.select(cam, tau)
    assert len(sel) == 1 and sel.depth[0] == 0  # k = c = 5: the root patch only
    rho = paper_precision(tau, cam.focal_px, 5)
    assert rho == pytest.approx(cam.focal_px / (6.0 * 32))
    for e, (length, d) in enumerate(_edge_distances(g, cam, 800.0, 800.0, 32)):
        assert sel.eps[0, e] == pytest.approx(rho * length / d, rel=1e-5)
        assert sel.edge_res[0, e] == edge_resolution(sel.eps[0, e], 5)
    assert sel.edge_res[0, 2] > sel.edge_res[0, 0] > 1  # near (south) finer than far
    # ours: a flat node is exact at any resolution (δ = 0 -> ε = 0, the coarsest tiles)
    sel_o, _ = ours.select(cam, tau)
    assert (sel_o.eps == 0).all() and ours.draw(cam, sel_o).triangles == 8
    assert paper.draw(cam, sel).triangles > 8
    # both draw the flat plane exactly
    assert paper.screen_errors(cam, sel).max() < 1e-6


def test_paper_rho_ignores_the_data(tmp_path):
    # the same grid, flat or rough: ρ is one factor, so ε differs only through d (z ranges)
    g_rough = _strategy(tile_dem(_mkdir(tmp_path, "r"), rough(33, 5), 33), 5, rho="paper")
    g_flat = _strategy(
        tile_dem(_mkdir(tmp_path, "f"), np.full((33, 33), 800, np.int16), 33), 5, rho="paper"
    )
    cam = _nadir(X0 + 480, Y0 - 480, 5000.0)  # high above: d is nearly the height for both
    a, _ = g_rough.select(cam, 2.0)
    b, _ = g_flat.select(cam, 2.0)
    np.testing.assert_allclose(a.eps, b.eps, rtol=0.05)
    np.testing.assert_array_equal(a.edge_res, b.edge_res)


def test_rho_must_be_a_known_form(rough_store):
    with pytest.raises(RenderError, match="rho"):
        _strategy(rough_store, rho="roughness")


@pytest.fixture(scope="module")
def boundary_view(tmp_path_factory):
    """A store and an oblique camera whose paper-ρ selection has level boundaries (the view of
    tests/render/test_cracks.py), with the full-resolution reference and its footprint."""
    path = tile_dem(tmp_path_factory.mktemp("paper"), rough(257, 5, amp=20.0), 65)
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    x0, y0, x1, _ = r.grid.extent
    cam = Camera(((x0 + x1) / 2, y0 + 1500, 3000.0), pitch=-30.0, viewport=SIZE, near=5.0, far=1e5)
    ref, _ = r.select(cam, 0.0, full=True)
    r.draw(cam, ref, clear=CLEAR)
    footprint = ~measure.is_clear(r.image(), CLEAR)
    yield r, cam, ref, footprint
    r.close()


@pytest.mark.parametrize("tau", [1.0, 4.0])
def test_paper_rho_is_crack_free_and_unstitched_is_the_control(boundary_view, tau):
    r, cam, ref, footprint = boundary_view
    st = get_strategy("seamless-patches", r, rho="paper")
    out = {}
    for stitching in (False, True):
        st.stitching = stitching
        sel, _ = st.select(cam, tau)
        counts = st.counts(sel)
        assert counts.max_level > counts.min_level, "the view must have level boundaries"
        assert sel.violations == 0
        wt = cracks.watertight(r.grid, *st.triangles(cam, sel))
        out[stitching] = (wt, drawn_cracks(r, st, cam, sel, ref, footprint))
    wt, (here, above) = out[False]  # positive control: every detector fires
    assert wt.gap_edges > 0 and wt.open_edges >= wt.gap_edges and wt.max_gap_m > 1.0
    assert here > 0 and above > 0
    wt, (here, above) = out[True]
    assert (wt.open_edges, wt.gap_edges, wt.max_gap_m) == (0, 0, 0.0)
    assert wt.boundary_edges > 0 and here == 0 and above == 0


def test_tradeoff_measures_the_form_of_rho_it_is_given(boundary_view):
    r, cam, _, _ = boundary_view
    rows = {
        form: tradeoff(
            r.store, cam, [4.0], renderer=r, repeats=1, lod="seamless-patches", stream_tau=0.0,
            lod_options={"rho": form},
        )[0]
        for form in ("bound", "paper")
    }  # fmt: skip
    with open_render_session(r.store, 0.0, "conservative", r.p) as s:
        _, res = stream_step(s, None, cam)  # the levels tradeoff's selection saw
    for form, row in rows.items():
        st = get_strategy("seamless-patches", r, rho=form)
        sel, _ = st.select(cam, 4.0, resident=res)
        assert row.triangles == st.triangle_count(sel) > 0, form
        assert (row.crack_pixels, row.open_edges, row.gap_edges) == (0, 0, 0)
    assert rows["bound"].triangles != rows["paper"].triangles
