"""One sample, one error: measured screen error counts each full-resolution sample in view once,
whichever way a strategy gives its drawn surface."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies.base import GlobalHeights, triangle_screen_errors
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (128, 96)


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    ctx = make_context()
    s = open_store(tile_dem(tmp_path_factory.mktemp("err"), rough(129, 3), 33))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=ctx)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield r
    r.close()


def _camera() -> Camera:
    return Camera(
        (500015.0 + 1920, 4998000.0 - 1500, 1500.0),
        pitch=-40.0,
        viewport=SIZE,
        near=5.0,
        far=1e5,
    )


def test_patch_twin_and_triangle_readback_count_the_same_samples(renderer):
    r, cam = renderer, _camera()
    p, _ = r.select(cam, 2.0)
    assert p.snap.max() > 0 and len(np.unique(p.level)) >= 2  # snapped strips are in view
    heights = measure.heights_fn(r.store, p)
    a = measure.screen_errors(p, r.grid, cam, heights)  # qiu's CPU twin, patch by patch
    tri, h = measure.patch_triangles(p, r.grid, heights)  # the same mesh as triangles
    b = triangle_screen_errors(r.grid, cam, tri, h, GlobalHeights(r.store))
    sa, sb = measure.error_stats(a), measure.error_stats(b)
    assert sa.samples == sb.samples > 1000
    assert sa.max_px == pytest.approx(sb.max_px, abs=1e-9)
    assert sa.p99_px == pytest.approx(sb.p99_px, abs=1e-9)
    assert sa.mean_px == pytest.approx(sb.mean_px, abs=1e-9)


def test_each_sample_is_counted_once(renderer):
    r, cam = renderer, _camera()
    p, _ = r.select(cam, 2.0)
    heights = measure.heights_fn(r.store, p)
    tri, h = measure.patch_triangles(p, r.grid, heights)
    rows, cols, _ = measure.rasterise(*_finite(tri, h))
    x, y = r.grid.sample_xy(rows, cols)
    _, _, _, keep = measure.project_in_view(cam, x, y, GlobalHeights(r.store)(rows, cols))
    distinct = len(np.unique(rows[keep] * 100000 + cols[keep]))
    assert len(keep) > distinct  # shared edges are rasterised more than once ...
    err = triangle_screen_errors(r.grid, cam, tri, h, GlobalHeights(r.store))
    assert len(err) == distinct  # ... and measured once


def _finite(tri, h):
    ok = np.isfinite(h).all(axis=1)
    return tri[ok], h[ok]


def test_crack_pixels_leave_out_holes_in_the_data():
    """An enclosed clear pixel inside the footprint is a crack, unless ``holes`` marks it (the
    selection covers it once its nodata holes are drawn); a clear pixel joined to the
    background never counts."""
    clear = (255, 0, 255)
    img = np.zeros((6, 8, 3), np.uint8)
    img[0, :] = clear  # background along the top: reachable
    img[3, 2] = clear  # enclosed
    img[3, 5] = clear  # enclosed
    footprint = np.ones((6, 8), bool)
    assert measure.crack_pixels(img, footprint, clear) == 2
    holes = np.zeros((6, 8), bool)
    holes[3, 5] = True
    assert measure.crack_pixels(img, footprint, clear, holes=holes) == 1
    holes[0, :] = True  # marking background pixels changes nothing
    assert measure.crack_pixels(img, footprint, clear, holes=holes) == 1
