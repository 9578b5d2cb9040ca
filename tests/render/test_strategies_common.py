"""What every registered LOD strategy must do (issue #5): the renderer's known-answer scenes,
no cracks straight down at every τ, the full mesh at τ = 0, the coarsest mesh at a huge τ, the
exact surface at τ = 0, and a measured error. Strategy-specific answers live in
``test_strategy_<name>.py``."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.pipeline import tradeoff
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import OWN_ERROR, get_strategy, strategy_class, strategy_names
from render.strategies.base import GlobalHeights
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15
NAMES = strategy_names()
#: options that make a 32-cell block interesting for a strategy
OPTIONS = {
    "chunk-tessellation": {"chunk_log2": 3},
    "chunk-tessellation-gpu": {"chunk_log2": 3},
    "seamless-patches": {"res_log2": 3},
}


def _strategy(path, name, size=SIZE):
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=size, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    return get_strategy(name, r, **OPTIONS.get(name, {}))


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


@pytest.fixture(scope="module")
def peak_store(tmp_path_factory):
    dem = np.zeros((65, 65), np.int16)
    dem[30:35, 40:45] = 400
    return tile_dem(tmp_path_factory.mktemp("peak"), dem, 65)


def _nadir(x, y, h, yaw=0.0, size=SIZE) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=size, near=5.0, far=5e4)


@pytest.mark.parametrize("name", NAMES)
def test_flat_block_renders_a_uniform_surface(tmp_path, name):
    st = _strategy(tile_dem(tmp_path, np.full((33, 33), 100, np.int16), 33), name)
    cam = _nadir(X0 + 480, Y0 - 480, 600.0)
    for tau in (0.0, 1.0):
        sel, _ = st.select(cam, tau)
        stats = st.draw(cam, sel)
        img = st.r.image()
        assert stats.triangles >= 2
        assert (img == img[0, 0]).all() and not measure.is_clear(img, st.r.config.clear).any()
    err = st.screen_errors(cam, st.select(cam, 1.0)[0])
    assert err.size > 0 and err.max() < 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_known_peak_appears_at_the_predicted_pixel(peak_store, name):
    st = _strategy(peak_store, name)
    g = st.r.grid
    peak = np.array([g.x0 + 42 * g.dx, g.y0 - 32 * g.dy, 400.0])
    cam = Camera.look_at(
        (g.x0 + 960, g.y0 - 2600, 1500.0), (g.x0 + 960, g.y0 - 960, 0.0), viewport=SIZE,
        near=5.0, far=1e4,
    )  # fmt: skip
    sel, _ = st.select(cam, 0.0)
    st.draw(cam, sel)
    img = st.r.image().astype(int)
    px, py, _ = cam.project(peak[None])
    assert img[int(py[0]), int(px[0])].sum() > 500
    ground = cam.project(np.array([[g.x0 + 10 * g.dx, g.y0 - 32 * g.dy, 0.0]]))
    assert img[int(ground[1][0]), int(ground[0][0])].sum() < 400


@pytest.mark.parametrize("tau", [0.5, 1, 2, 4, 8])
@pytest.mark.parametrize("name", NAMES)
def test_no_cracks_looking_straight_down(rough_store, name, tau):
    st = _strategy(rough_store, name)
    cx, cy = X0 + 1920, Y0 - 1920  # a corner shared by 4 blocks
    for h, yaw, dx in ((1400.0, 0.0, 0.0), (1800.0, 30.0, 250.0), (2600.0, 0.0, -400.0)):
        cam = _nadir(cx + dx, cy + dx / 2, h, yaw)
        sel, _ = st.select(cam, tau)
        st.draw(cam, sel, clear=CLEAR)
        assert not measure.is_clear(st.r.image(), CLEAR).any(), (name, h)
    # an oblique selection (several levels side by side) seen from straight above
    obl = Camera((cx, cy - 1500, 1500.0), pitch=-60.0, viewport=SIZE, near=5.0, far=1e5)
    sel, _ = st.select(obl, tau)
    nad = _nadir(cx, cy, 1300.0)
    st.draw(nad, sel, clear=CLEAR)
    img = st.r.image()
    ref, _ = st.r.select(nad, 0.0, full=True)
    st.r.draw(nad, ref, clear=CLEAR)
    fp = ~measure.is_clear(st.r.image(), CLEAR)
    assert measure.crack_pixels(img, fp, CLEAR) == 0


@pytest.mark.parametrize("name", NAMES)
def test_tau_zero_draws_the_full_mesh_and_huge_tau_fewer(rough_store, name):
    st = _strategy(rough_store, name)
    cam = _nadir(X0 + 1920, Y0 - 1920, 9000.0)  # the whole 4 x 4 block store in view
    sel, _ = st.select(cam, 0.0)
    full = st.draw(cam, sel).triangles
    assert full == 16 * 2 * 32 * 32
    ref, _ = st.r.select(cam, 0.0, full=True)
    assert full == st.r.draw(cam, ref).triangles
    mid = st.draw(cam, st.select(cam, 1.0)[0]).triangles
    coarse = st.draw(cam, st.select(cam, 1e9)[0]).triangles
    assert 16 * 2 <= coarse <= mid < full
    assert st.drawn_blocks(sel) == set(st.r.store.blocks())
    assert st.used_levels(cam, sel) == {b: 5 for b in st.r.store.blocks()}
    coarse_levels = st.used_levels(cam, st.select(cam, 1e9)[0])
    assert set(coarse_levels) == set(st.r.store.blocks()) and max(coarse_levels.values()) < 5


@pytest.mark.parametrize("name", NAMES)
def test_tau_zero_surface_is_the_terrain(rough_store, name):
    st = _strategy(rough_store, name)
    cam = Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )
    sel, _ = st.select(cam, 0.0)
    rows, cols, h = st.surface(cam, sel)
    assert rows.size > 5000
    np.testing.assert_allclose(h, GlobalHeights(st.r.store)(rows, cols), atol=1e-3)
    assert st.screen_errors(cam, sel).max() < 1e-3


@pytest.mark.parametrize("name", NAMES)
def test_measured_error_is_reported_and_grows_with_tau(rough_store, name):
    st = _strategy(rough_store, name)
    cam = Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )
    errs = []
    for tau in (0.5, 8.0):
        sel, ms = st.select(cam, tau)
        err = st.screen_errors(cam, sel)
        assert err.size > 5000 and np.isfinite(err).all() and ms >= 0
        errs.append(err.max())
    assert 0 <= errs[0] <= errs[1] < 80.0 and errs[1] > 0


@pytest.mark.parametrize("name", NAMES)
def test_tradeoff_row_through_the_streaming_session(rough_store, name):
    s = open_store(rough_store)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    cam = Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )
    rows = tradeoff(s, cam, [1.0], patch_log2=2, renderer=r, repeats=1, lod=name)
    row = rows[0]
    assert row.strategy == name and row.crack_pixels == 0
    assert row.triangles > 0 and row.samples_in_view > 5000
    # the row names what τ bounded: Eq. 7 only for the strategy that selects with it
    assert row.metric == ("qiu" if strategy_class(name).uses_metric else OWN_ERROR)


@pytest.mark.parametrize("name", NAMES)
def test_translated_by_1e7_renders_the_same_image(tmp_path, name):
    dem = rough(65, 5)
    imgs, tris = [], []
    for i, shift in enumerate((0.0, 1e7)):
        d = tmp_path / str(i)
        d.mkdir()
        st = _strategy(tile_dem(d, dem, 33, origin=(500000.0 + shift, 5000000.0 + shift)), name)
        g = st.r.grid
        cam = Camera.look_at(
            (g.x0 + 200, g.y0 - 2400, 1400.0), (g.x0 + 1000, g.y0 - 900, 700.0), viewport=SIZE,
            near=5.0, far=1e5,
        )  # fmt: skip
        sel, _ = st.select(cam, 1.0)
        tris.append(st.draw(cam, sel).triangles)
        imgs.append(st.r.image())
    assert tris[0] == tris[1]
    assert measure.changed_share(imgs[0], imgs[1], threshold=0) <= 0.002


@pytest.mark.parametrize("name", NAMES)
def test_nodata_is_hidden_at_full_resolution(tmp_path, name):
    # rough terrain (so every strategy refines to full resolution at tau = 0) with a hole;
    # coarser meshes may bridge a hole smaller than their cells (docs/RENDER.md, nodata)
    dem = rough(65, 5).astype(np.float32)
    dem[20:30, 20:30] = np.nan
    st = _strategy(tile_dem(tmp_path, dem, 33, nodata=np.nan), name)
    g = st.r.grid
    cx, cy, z = g.x0 + 24.5 * g.dx, g.y0 - 24.5 * g.dy, float(np.nanmean(dem))
    cam = Camera.look_at((cx, cy - 500.0, z + 2000.0), (cx, cy, z), viewport=SIZE, near=5.0)
    sel, _ = st.select(cam, 0.0)
    st.draw(cam, sel, clear=CLEAR)
    clear = measure.is_clear(st.r.image(), CLEAR)
    hole = cam.project(np.array([[cx, cy, z]]))
    hx, hy = int(hole[0][0]), int(hole[1][0])
    assert clear[hy - 1 : hy + 2, hx - 1 : hx + 2].all()  # ~10 px wide in this view
    ref, _ = st.r.select(cam, 0.0, full=True)
    st.r.draw(cam, ref, clear=CLEAR)
    assert (clear == measure.is_clear(st.r.image(), CLEAR)).mean() > 0.995  # as the reference
    rows, cols, h = st.surface(cam, sel)
    drawn = (rows >= 20) & (rows < 30) & (cols >= 20) & (cols < 30)
    assert not np.isfinite(h[drawn]).any()  # no drawn height inside the hole
