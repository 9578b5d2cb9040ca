"""Cracks measured on what is drawn: the exact watertightness figure (pure) and, for every
strategy, positive controls — stitching switched off on a view that has level boundaries makes
every crack detector fire; switched on, they read 0."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import cracks, measure
from render.pipeline import drawn_cracks
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import get_strategy, strategy_names
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.store import open_store

GRID = BlockGrid(height=65, width=65, k=6, x0=0.0, y0=640.0, dx=10.0, dy=10.0)


def _quad(h_mid: float) -> tuple[np.ndarray, np.ndarray]:
    """A coarse triangle pair on the left (one long edge x=2) and two fine triangle pairs on
    the right sharing a T-vertex (2, 1) of height ``h_mid`` (the long edge interpolates 1)."""
    tri = np.array(
        [
            [[0, 0], [2, 0], [2, 2]],
            [[0, 0], [2, 2], [0, 2]],
            [[2, 0], [3, 0], [2, 1]],
            [[3, 0], [3, 1], [2, 1]],
            [[2, 1], [3, 1], [2, 2]],
            [[3, 1], [3, 2], [2, 2]],
        ]
    )
    hv = {(0, 0): 0.0, (2, 0): 0.0, (2, 2): 2.0, (0, 2): 2.0, (3, 0): 0.0, (3, 1): 1.0, (3, 2): 2.0}
    hv[(2, 1)] = h_mid
    h = np.array([[hv[tuple(p)] for p in t] for t in tri.tolist()])
    return tri, h


def test_shared_edges_and_the_outline_are_not_open():
    tri = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]])
    w = cracks.watertight(GRID, tri, np.zeros((2, 3)))
    assert (w.open_edges, w.gap_edges, w.boundary_edges, w.max_gap_m) == (0, 0, 4, 0.0)


def test_a_t_junction_on_the_long_edge_is_open_but_closed():
    w = cracks.watertight(GRID, *_quad(1.0))  # the T-vertex lies on the long edge
    assert w.open_edges == 3 and w.gap_edges == 0 and w.max_gap_m == 0.0


def test_a_t_junction_off_the_long_edge_is_a_gap():
    w = cracks.watertight(GRID, *_quad(4.5))
    assert w.open_edges == 3 and w.gap_edges == 3
    assert w.max_gap_m == pytest.approx(3.5) and w.longest_gap_m == pytest.approx(20.0)


def test_hidden_and_degenerate_triangles_are_left_out():
    tri, h = _quad(4.5)
    h[0, 0] = np.nan  # hide the coarse pair's first triangle: its edges leave the mesh
    w = cracks.watertight(GRID, tri, h)
    assert w.triangles == 5
    flat = np.array([[[0, 0], [1, 1], [2, 2]]])  # zero area
    assert cracks.watertight(GRID, flat, np.zeros((1, 3))).triangles == 0


def test_a_vertex_drawn_at_two_heights_is_a_gap():
    tri = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]])
    h = np.zeros((2, 3))
    h[1, 1] = 0.25  # (1, 1) at 0 in one triangle, 0.25 in the other
    assert cracks.watertight(GRID, tri, h).max_gap_m == pytest.approx(0.25)


# -- every strategy, on a view with level boundaries ---------------------------------------

SIZE = (128, 96)
TAU = 8.0


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    ctx = make_context()
    s = open_store(tile_dem(tmp_path_factory.mktemp("cracks"), rough(257, 5, amp=20.0), 65))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=ctx)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    x0, y0, x1, _ = r.grid.extent
    cam = Camera(((x0 + x1) / 2, y0 + 1500, 3000.0), pitch=-30.0, viewport=SIZE, near=5.0, far=1e5)
    ref, _ = r.select(cam, 0.0, full=True)
    r.draw(cam, ref, clear=CLEAR)
    footprint = ~measure.is_clear(r.image(), CLEAR)
    yield r, cam, ref, footprint
    r.close()


def _measure(setup, name: str, stitching: bool):
    r, cam, ref, footprint = setup
    st = get_strategy(name, r)
    st.stitching = stitching
    sel, _ = st.select(cam, TAU)
    counts = st.counts(sel)
    assert counts.max_level > counts.min_level, "the view must have level boundaries"
    wt = cracks.watertight(r.grid, *st.triangles(cam, sel))
    return wt, drawn_cracks(r, st, cam, sel, ref, footprint)


@pytest.mark.gl
@pytest.mark.parametrize("name", strategy_names())
def test_unstitched_selection_cracks(setup, name):
    wt, (here, above) = _measure(setup, name, stitching=False)
    assert wt.gap_edges > 0 and wt.open_edges >= wt.gap_edges and wt.max_gap_m > 1.0
    assert here > 0 and above > 0


@pytest.mark.gl
@pytest.mark.parametrize("name", strategy_names())
def test_stitched_selection_is_watertight(setup, name):
    wt, (here, above) = _measure(setup, name, stitching=True)
    assert (wt.open_edges, wt.gap_edges, wt.max_gap_m) == (0, 0, 0.0)
    assert wt.boundary_edges > 0 and here == 0
    if name != "jung-han":
        assert above == 0


@pytest.mark.gl
@pytest.mark.xfail(
    strict=True,
    reason="jung-han's closed mesh (0 open edges) drops a pixel seen from above on llvmpipe",
)
def test_jung_han_from_above_has_no_crack_pixel(setup):
    _, (_, above) = _measure(setup, "jung-han", stitching=True)
    assert above == 0
