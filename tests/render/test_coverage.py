"""Coverage of the in-view terrain and nodata by the drawn surface; a view without terrain is an
error; samples the near plane clips are counted."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, tile_dem

from render import coverage, measure
from render.renderer import RenderConfig, TerrainRenderer
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (128, 96)


def _renderer(tmp, island: bool = False) -> TerrainRenderer:
    """A sloping 65² DEM with a 10² nodata hole (and, with ``island``, one valid sample left
    alone inside it), every block on the GPU at full resolution."""
    dem = np.full((65, 65), 300.0, np.float32)
    dem += np.add.outer(np.arange(65), np.arange(65)).astype(np.float32)
    dem[20:30, 20:30] = np.nan
    if island:
        dem[25, 25] = 350.0
    s = open_store(tile_dem(tmp, dem, 33, nodata=np.nan))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=make_context())
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    return r


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    r = _renderer(tmp_path_factory.mktemp("cov"))
    yield r
    r.close()


def _nadir(r, h: float = 2500.0, near: float = 5.0) -> Camera:
    g = r.grid
    pos = (g.x0 + 32 * g.dx, g.y0 - 32 * g.dy, h)
    return Camera(pos, pitch=-90.0, viewport=SIZE, near=near, far=5e4)


def _cov(r, cam, tri, h):
    ref, _ = r.select(cam, 0.0, full=True)
    return coverage.coverage(r.grid, cam, ref, measure.heights_fn(r.store, ref), tri, h)


def _drawn(r, cam, tau):
    p, _ = r.select(cam, tau, full=tau == 0)
    return measure.patch_triangles(p, r.grid, measure.heights_fn(r.store, p))


def test_the_drawn_surface_covers_the_terrain_and_not_the_hole(renderer):
    r = renderer
    cam = _nadir(r)
    c = _cov(r, cam, *_drawn(r, cam, 0.0))
    assert c.terrain_in_view > 3000 and c.nodata_in_view == 100
    assert c.terrain_covered == 1.0 and c.nodata_covered == 0.0 and c.near_clipped == 0


def test_dropped_triangles_and_a_covered_hole_are_seen(renderer):
    r = renderer
    cam = _nadir(r)
    tri, h = _drawn(r, cam, 0.5)
    half = _cov(r, cam, tri[::2], h[::2])  # every other triangle dropped
    assert half.terrain_covered < 0.9
    g = r.grid
    n = 64
    lid = np.array([[[0, 0], [n, 0], [n, n]], [[0, 0], [n, n], [0, n]]])  # two big triangles
    c = _cov(r, cam, lid, np.full((2, 3), 300.0))
    assert c.nodata_covered == 1.0 and c.terrain_covered == 1.0 and g.k == 5


def test_a_view_without_terrain_is_an_error(renderer):
    r = renderer
    g = r.grid
    sky = Camera((g.x0 + 32 * g.dx, g.y0 - 32 * g.dy, 2500.0), pitch=60.0, viewport=SIZE)
    ref, _ = r.select(_nadir(r), 0.0, full=True)  # blocks exist, none in this view
    with pytest.raises(coverage.EmptyViewError, match="no terrain sample"):
        coverage.coverage(r.grid, sky, ref, measure.heights_fn(r.store, ref), *_drawn(r, sky, 1))


def test_samples_nearer_than_the_near_plane_are_counted(renderer):
    r = renderer
    g = r.grid
    pos = (g.x0 + 32 * g.dx, g.y0 - 64 * g.dy - 600.0, 900.0)  # south, looking north
    far = Camera(pos, pitch=-30.0, viewport=SIZE, near=5.0, far=5e4)
    near = Camera(pos, pitch=-30.0, viewport=SIZE, near=1000.0, far=5e4)
    tri, h = _drawn(r, _nadir(r), 0.5)
    ref, _ = r.select(_nadir(r), 0.0, full=True)
    heights = measure.heights_fn(r.store, ref)
    a = coverage.coverage(r.grid, far, ref, heights, tri, h)
    b = coverage.coverage(r.grid, near, ref, heights, tri, h)
    assert a.near_clipped == 0 and b.near_clipped > 100
    assert b.terrain_in_view + b.near_clipped == a.terrain_in_view


def test_uncovered_px_known_answer_and_control(renderer):
    """A hole of 3 × 3 samples in the covered set: its centre is 2 samples from the nearest
    covered one, ``f 2 dx / depth`` px straight down; full cover gives 0 (quiet case)."""
    r = renderer
    g = r.grid
    cam = _nadir(r)
    wg = g.cols * g.step + 1
    rows, cols = np.mgrid[40:61, 40:61]
    keys = (rows * wg + cols).ravel()
    heights = np.full(keys.shape, 300.0)
    covered = ~((abs(rows - 50) <= 1) & (abs(cols - 50) <= 1)).ravel()
    got = coverage.uncovered_px(g, cam, keys, heights, covered)
    assert got == pytest.approx(cam.focal_px * 2 * g.dx / (2500.0 - 300.0), rel=1e-6)
    assert coverage.uncovered_px(g, cam, keys, heights, np.ones(keys.shape, bool)) == 0.0
    assert coverage.uncovered_px(g, cam, keys, heights, covered, radius=0) == float("inf")


def test_dropped_triangles_are_far_from_the_drawn_terrain(renderer):
    """Positive control for the figure a view reports: every other triangle dropped leaves
    uncovered samples a pixel or more from the drawn terrain; the full mesh leaves none."""
    r = renderer
    cam = _nadir(r)
    tri, h = _drawn(r, cam, 0.0)
    assert _cov(r, cam, tri, h).uncovered_px == 0.0
    assert _cov(r, cam, tri[::2], h[::2]).uncovered_px >= 1.0


@pytest.fixture(scope="module")
def islanded(tmp_path_factory):
    """:func:`renderer`'s DEM with one valid sample left alone inside its hole: no triangle,
    at any resolution, can draw it (every triangle holding it has a nodata corner)."""
    r = _renderer(tmp_path_factory.mktemp("island"), island=True)
    yield r
    r.close()


def test_terrain_no_triangle_can_draw_is_not_counted_as_dropped(islanded):
    """The lone sample, in view, is not drawn even at full resolution: it is reported as
    ``undrawable`` and left out of the shares, so the full-resolution surface covers all the
    terrain and its undrawn distance is 0 (it read the island's distance to the hole's rim,
    ~5 cells, before). Controls: dropping drawable triangles still lowers the share and raises
    the distance; a DEM without the island has nothing undrawable."""
    r = islanded
    cam = _nadir(r)
    g = r.grid
    ref, _ = r.select(cam, 0.0, full=True)
    terrain, _, _ = coverage.in_view_samples(ref, g, cam, measure.heights_fn(r.store, ref))
    island = 25 * (g.cols * g.step + 1) + 25
    assert island in terrain  # in view, and no full-resolution triangle draws it:
    assert island not in coverage.reference_cover(g, ref, measure.heights_fn(r.store, ref))
    full = _cov(r, cam, *_drawn(r, cam, 0.0))
    assert full.undrawable == 1
    assert full.terrain_covered == 1.0 and full.uncovered_px == 0.0
    tri, h = _drawn(r, cam, 0.0)
    keep = ~((tri[:, :, 0] >= 40) & (tri[:, :, 1] >= 40)).all(axis=1)  # a corner dropped
    dropped = _cov(r, cam, tri[keep], h[keep])
    assert dropped.undrawable == 1 and dropped.terrain_covered < 1.0
    assert dropped.uncovered_px > 5.0


def test_no_undrawable_terrain_without_islands(renderer):
    r = renderer
    cam = _nadir(r)
    tri, h = _drawn(r, cam, 0.0)
    c = _cov(r, cam, tri[::2], h[::2])  # drawn terrain missed: the reference cover is read
    assert c.undrawable == 0 and c.terrain_covered < 1.0


def test_reference_cover_of_some_samples_reads_only_their_patches(islanded, monkeypatch):
    """``reference_cover`` restricted to some samples (the missed ones, in practice) equals the
    whole cover cut to them, block borders, the island and the hole included, and rasterises
    only the patches that hold them."""
    r = islanded
    g = r.grid
    cam = _nadir(r)
    ref, _ = r.select(cam, 0.0, full=True)
    heights = measure.heights_fn(r.store, ref)
    whole = coverage.reference_cover(g, ref, heights)
    wg = g.cols * g.step + 1
    rng = np.random.default_rng(3)
    picks = [(25, 25), (20, 20), (32, 32), (32, 10), (0, 0), (64, 64), (29, 30)]
    picks += [tuple(p) for p in rng.integers(0, 65, (30, 2))]
    keys = np.unique([rr * wg + cc for rr, cc in picks])
    seen = []
    real = measure.patch_triangles

    def counted(patches, *a):
        seen.append(len(patches))
        return real(patches, *a)

    monkeypatch.setattr(measure, "patch_triangles", counted)
    part = coverage.reference_cover(g, ref, heights, keys)
    assert np.array_equal(part, whole[np.isin(whole, keys)])
    assert 25 * wg + 25 not in part and seen[0] < len(ref) / 2


@pytest.mark.parametrize("hole", [False, True])
def test_the_stores_padding_is_not_nodata(tmp_path, hole):
    """A 50² DEM in 33² blocks: rows and columns 50–64 of the last blocks are padding. They
    were counted as in-view nodata on a DEM without any; the DEM's own hole still is."""
    dem = np.full((50, 50), 300.0, np.float32)
    dem += np.add.outer(np.arange(50), np.arange(50)).astype(np.float32)
    if hole:
        dem[10:15, 10:15] = np.nan
    s = open_store(tile_dem(tmp_path, dem, 33, nodata=np.nan))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=make_context())
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    g = r.grid
    assert (g.height, g.width, g.rows * g.step + 1) == (50, 50, 65)  # padded
    cam = Camera((g.x0 + 32 * g.dx, g.y0 - 32 * g.dy, 2500.0), pitch=-90.0, viewport=SIZE)
    c = _cov(r, cam, *_drawn(r, cam, 0.0))
    r.close()
    assert c.terrain_in_view + c.undrawable == 50 * 50 - (25 if hole else 0)  # all in view
    assert c.nodata_in_view == (25 if hole else 0)
