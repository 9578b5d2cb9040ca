"""``chunk-tessellation`` (Kim, Lee & Shin) and the strategy interface, on headless EGL."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import (
    UnknownStrategyError,
    get_strategy,
    strategy_names,
)
from render.strategies.chunk_tess import batch_chunks
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15


def _strategy(path, chunk_log2: int = 3, size=SIZE, name="chunk-tessellation"):
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=size, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    opts = {"chunk_log2": chunk_log2} if name == "chunk-tessellation" else {}
    return get_strategy(name, r, **opts)


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


def _nadir(x, y, h, yaw=0.0, size=SIZE) -> Camera:
    return Camera((x, y, h), yaw=yaw, pitch=-90.0, viewport=size, near=5.0, far=5e4)


def test_unknown_strategy_lists_the_choices(rough_store):
    st = _strategy(rough_store)
    with pytest.raises(UnknownStrategyError, match="qiu, chunk-tessellation"):
        get_strategy("nope", st.r)
    assert strategy_names()[0] == "qiu"


def test_qiu_strategy_is_the_renderer(rough_store):
    st = _strategy(rough_store, name="qiu")
    cam = _nadir(X0 + 1920, Y0 - 1920, 1800.0)
    p, _ = st.select(cam, 1.0)
    q, _ = st.r.select(cam, 1.0)
    a = st.draw(cam, p)
    b = st.r.draw(cam, q)
    assert a.triangles == b.triangles and len(p) == len(q)


def test_flat_block_renders_a_uniform_surface(tmp_path):
    st = _strategy(tile_dem(tmp_path, np.full((33, 33), 100, np.int16), 33))
    cam = _nadir(X0 + 480, Y0 - 480, 600.0)
    p, _ = st.select(cam, 1.0)
    stats = st.draw(cam, p)
    img = st.r.image()
    assert len(p) == 1 and stats.triangles == 128  # the root chunk, 8 x 8 cells of level 3
    assert (img == img[0, 0]).all() and not measure.is_clear(img, st.r.config.clear).any()


def test_known_peak_appears_at_the_predicted_pixel(tmp_path):
    dem = np.zeros((65, 65), np.int16)
    dem[30:35, 40:45] = 400
    st = _strategy(tile_dem(tmp_path, dem, 65))
    g = st.r.grid
    peak = np.array([g.x0 + 42 * g.dx, g.y0 - 32 * g.dy, 400.0])
    cam = Camera.look_at(
        (g.x0 + 960, g.y0 - 2600, 1500.0),
        (g.x0 + 960, g.y0 - 960, 0.0),
        viewport=SIZE,
        near=5.0,
        far=1e4,
    )
    p, _ = st.select(cam, 0.0)
    st.draw(cam, p)
    img = st.r.image().astype(int)
    px, py, _ = cam.project(peak[None])
    assert img[int(py[0]), int(px[0])].sum() > 500
    ground = cam.project(np.array([[g.x0 + 10 * g.dx, g.y0 - 32 * g.dy, 0.0]]))
    assert img[int(ground[1][0]), int(ground[0][0])].sum() < 400


def test_tessellated_triangles_match_the_formula_and_the_store(rough_store):
    st = _strategy(rough_store)
    cam = Camera.look_at(
        (X0 + 1900, Y0 - 4500, 1500.0), (X0 + 1900, 4998000, 800.0), viewport=SIZE, near=5.0
    )
    p, _ = st.select(cam, 1.0)
    assert p.snap.max() > 0 and len(np.unique(p.level)) > 1
    stats = st.draw(cam, p)
    tri, h = st.triangles(cam, p)
    assert len(tri) == stats.triangles
    full = np.zeros((129, 129))
    for b in st.r.store.blocks():
        full[b[0] * 32 : b[0] * 32 + 33, b[1] * 32 : b[1] * 32 + 33] = st.r.store.read_block(b)
    np.testing.assert_array_equal(h, full[tri[..., 1], tri[..., 0]])


@pytest.mark.parametrize("tau", [0.5, 1, 2, 4, 8])
def test_no_cracks_looking_straight_down(rough_store, tau):
    st = _strategy(rough_store)
    cx, cy = X0 + 1920, Y0 - 1920  # a corner shared by 4 blocks
    levels = set()
    for h, yaw, dx in ((1400.0, 0.0, 0.0), (1800.0, 30.0, 250.0), (2600.0, 0.0, -400.0)):
        cam = _nadir(cx + dx, cy + dx / 2, h, yaw)
        p, _ = st.select(cam, tau)
        st.draw(cam, p, clear=CLEAR)
        assert not measure.is_clear(st.r.image(), CLEAR).any(), (h, np.unique(p.level))
        levels |= set(np.unique(p.level).tolist())
    # an oblique selection (several levels, matched outer factors) seen from straight above
    obl = Camera((cx, cy - 1500, 1500.0), pitch=-60.0, viewport=SIZE, near=5.0, far=1e5)
    p, _ = st.select(obl, tau)
    nad = _nadir(cx, cy, 1300.0)
    st.draw(nad, p, clear=CLEAR)
    img = st.r.image()
    ref, _ = st.r.select(nad, 0.0, full=True)
    st.r.draw(nad, ref, clear=CLEAR)
    fp = ~measure.is_clear(st.r.image(), CLEAR)
    assert measure.crack_pixels(img, fp, CLEAR) == 0
    if len(np.unique(p.level)) > 1:
        assert p.snap.max() > 0


def test_tau_zero_draws_the_full_mesh_and_huge_tau_the_coarsest(rough_store):
    st = _strategy(rough_store)
    cam = _nadir(X0 + 1920, Y0 - 1920, 9000.0)  # the whole 4 x 4 block store in view
    p, _ = st.select(cam, 0.0)
    stats = st.draw(cam, p)
    assert (p.level == st.r.k).all()
    assert stats.triangles == 16 * 2 * 32 * 32
    ref, _ = st.r.select(cam, 0.0, full=True)
    assert stats.triangles == st.r.draw(cam, ref).triangles
    p, _ = st.select(cam, 1e9)
    stats = st.draw(cam, p)
    assert len(p) == 16 and (p.level == 3).all() and stats.triangles == 16 * 128


def test_measured_error_is_reported(rough_store):
    st = _strategy(rough_store)
    cam = Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    )
    p, _ = st.select(cam, 2.0)
    err = st.screen_errors(cam, p)
    assert err.size > 5000 and 0 < err.max() < 8.0


def test_read_back_of_more_than_65536_tessellated_vertices(tmp_path):
    # > 60 chunks of 32 x 32 cells: > 65,536 tessellated vertices, over llvmpipe's 16-bit limit for
    # one draw call feeding a geometry shader (the strategy batches its passes)
    st = _strategy(tile_dem(tmp_path, rough(257, 5), 257), chunk_log2=5)
    assert batch_chunks(5) == 60
    cam = Camera.look_at(
        (X0 + 3840, Y0 - 20000, 9000.0), (X0 + 3840, Y0 - 3840, 0.0), viewport=SIZE, near=5.0
    )
    p, _ = st.select(cam, 0.0)
    assert len(p) > 60 and (p.level == 8).all()
    tri, h = st.triangles(cam, p)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert len(tri) == len(p) * 2048 and (area == 1).all()  # every triangle half a cell
    full = st.r.store.read_block((0, 0)).astype(np.float64)
    np.testing.assert_array_equal(h, full[tri[..., 1], tri[..., 0]])
