"""``chunk-tessellation-gpu``: Kim, Lee & Shin's traversal on the GPU selects the same chunks
with the same neighbour levels as its CPU twin (``select_clod`` + ``stitch`` from the start
depth), under resident caps and height pages, and draws the same image (headless EGL)."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render.errors import RenderError
from render.gpu import HeightPool
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.chunk_tess import ChunkTessellation, start_depth, tess_triangles
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15
FIELDS = ("block", "depth", "row", "col", "level", "snap")

VIEWS = {
    "oblique": Camera.look_at(
        (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
    ),
    "low": Camera((X0 + 1920, Y0 - 3500, 150.0), yaw=20.0, pitch=-10.0, viewport=SIZE, near=5.0),
    "nadir": Camera((X0 + 1920, Y0 - 1920, 1400.0), pitch=-90.0, viewport=SIZE, near=5.0),
}


def _renderer(path, page_floats: int | None = None, levels=None) -> TerrainRenderer:
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    if page_floats is not None:
        r.pool.close()
        r.pool = HeightPool(CTX, s.k, max_page_floats=page_floats)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k if levels is None else levels[b]))
    return r


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)  # k = 5, 4 x 4 blocks


@pytest.fixture(scope="module")
def r(rough_store):
    return _renderer(rough_store)


def _sorted(p):
    o = np.lexsort((p.col, p.row, p.depth, p.block))
    return {f: getattr(p, f)[o] for f in FIELDS}


def _assert_same(st, cam, tau, resident=None):
    """The GPU selection equals the CPU twin's chunks and snaps; its counts are the twin's."""
    sel, _ = st.select(cam, tau, resident=resident)
    gp, cp = st.patches(sel), st.select_twin(cam, tau, resident)
    got, want = _sorted(gp), _sorted(cp)
    assert len(gp) == len(cp) > 0
    for f in FIELDS:
        np.testing.assert_array_equal(got[f], want[f], err_msg=f)
    c = st.counts(sel)
    assert c.triangles == int(tess_triangles(cp.cells_log2, cp.snap).sum())
    assert (c.clamped, c.violations) == (cp.clamped, cp.violations)
    assert (c.max_level, c.min_level) == (cp.level.max(), cp.level.min())
    return sel, cp


@pytest.mark.parametrize("chunk_log2", [2, 3])
@pytest.mark.parametrize("view", sorted(VIEWS))
def test_gpu_selection_is_the_cpu_selection(r, chunk_log2, view):
    st = get_strategy("chunk-tessellation-gpu", r, chunk_log2=chunk_log2)
    snapped = 0
    for tau in (0.5, 1.0, 2.0, 4.0):
        _, cp = _assert_same(st, VIEWS[view], tau)
        snapped += int((cp.snap > 0).sum())
        assert cp.depth.min() >= start_depth(r.k, chunk_log2)
    if view != "nadir":
        assert snapped > 0  # level boundaries: the neighbour levels are exercised
    if start_depth(r.k, chunk_log2) == 0:  # k <= 2c: the twin is the CPU variant itself
        cpu = get_strategy("chunk-tessellation", r, chunk_log2=chunk_log2)
        p, _ = cpu.select(VIEWS[view], 1.0)
        q = st.select_twin(VIEWS[view], 1.0)
        assert all((_sorted(p)[f] == _sorted(q)[f]).all() for f in FIELDS)


def test_resident_caps_and_level_boundaries_across_block_borders(r):
    st = get_strategy("chunk-tessellation-gpu", r, chunk_log2=2)
    blocks = r.store.blocks()
    caps = {b: (5, 3, 4, 1)[(b[0] + 2 * b[1]) % 4] for b in blocks}
    caps[(0, 0)] = -1  # not drawn: its neighbours' edges have no neighbour
    border = 0
    for view in ("oblique", "low"):
        for tau in (0.5, 2.0):
            _, cp = _assert_same(st, VIEWS[view], tau, resident=caps)
            assert cp.clamped > 0 and (0, 0) not in {tuple(b) for b in cp.blocks[cp.block]}
            edge = 1 << cp.depth
            on = np.stack([cp.row == 0, cp.col == edge - 1, cp.row == edge - 1, cp.col == 0], 1)
            border += int(((cp.snap > 0) & on).sum())
    assert border > 0  # coarser chunks across a block border are matched


def test_height_pages_draw_the_cpu_variants_image(rough_store):
    # blocks spread over several HeightPool pages: one draw per page, the same pixels
    rr = _renderer(rough_store, page_floats=3 * 33 * 33 * 2)
    assert len(rr.pool.pages) > 1
    gpu = ChunkTessellation(rr, chunk_log2=3, selection="gpu")
    cpu = ChunkTessellation(rr, chunk_log2=3)
    for view in ("oblique", "low"):
        cam = VIEWS[view]
        sel, _ = _assert_same(gpu, cam, 1.0)
        assert len({int(p) for p in sel.table[:, 5]}) > 1
        a = gpu.draw(cam, sel, clear=CLEAR)
        img = rr.image()
        p, _ = cpu.select(cam, 1.0)
        b = cpu.draw(cam, p, clear=CLEAR)
        assert a.triangles == b.triangles and a.patches == b.patches
        np.testing.assert_array_equal(img, rr.image())
        tri, _ = gpu.triangles(cam, sel)
        assert len(tri) == a.triangles
        assert gpu.used_levels(cam, sel) == cpu.used_levels(cam, p)
        assert gpu.drawn_blocks(sel) == cpu.drawn_blocks(p)
    rr.close()


def test_stitching_off_zeroes_the_gpu_snaps(r):
    st = get_strategy("chunk-tessellation-gpu", r, chunk_log2=3)
    sel, _ = st.select(VIEWS["oblique"], 4.0)
    assert st.patches(sel).snap.max() > 0
    st.stitching = False
    off, _ = st.select(VIEWS["oblique"], 4.0)
    p = st.patches(off)
    assert p.snap.max() == 0 and len(p) == len(st.patches(sel))
    assert st.counts(off).triangles == int(tess_triangles(p.cells_log2, p.snap).sum())


def test_bad_selection_is_named(r):
    with pytest.raises(RenderError, match="selection must be one of"):
        ChunkTessellation(r, selection="fpga")
