"""A triangle with a nodata corner is not drawn at all (audit 44b).

A DEM whose every cell has a nodata corner (a checkerboard of nodata samples, or every other
column nodata) rendered a handful of terrain pixels and exit 0: the fragment shader discarded
fragments by an interpolated "masked" varying, which is exactly 0 on the edge between a
triangle's two terrain corners, so pixels whose centres lay on such an edge were drawn. The
vertex stage now gives masked vertices clip distance -1 (``render/glsl/emit.glsl``): such a
triangle is clipped to a line or a point, which has no area. ``render`` then fails naming the
cause (no cell with four terrain corners).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from gltools import make_context, tile_dem
from typer.testing import CliRunner

from cli.main import app
from render.frame import CLEAR
from render.strategies import get_strategy, strategy_names
from render.views import overview_camera, terrain_cells

pytestmark = pytest.mark.gl
make_context()
runner = CliRunner()
SIZE = (128, 96)


def _surface(n: int = 65) -> np.ndarray:
    from demtools import fractal

    return fractal((n, n), seed=4, dtype="float32")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """Stores (blocks of 65): ``checker`` (every other sample nodata, checkerboard),
    ``columns`` (every other column nodata), ``hole`` (a nodata rectangle), ``plain``."""
    z = _surface()
    rows, cols = np.indices(z.shape)
    checker, columns, hole = z.copy(), z.copy(), z.copy()
    checker[(rows + cols) % 2 == 1] = -9999.0
    columns[:, 1::2] = -9999.0
    hole[20:40, 25:45] = -9999.0
    out = {}
    for name, data, nd in [
        ("checker", checker, -9999.0),
        ("columns", columns, -9999.0),
        ("hole", hole, -9999.0),
        ("plain", z, None),
    ]:
        tmp = tmp_path_factory.mktemp(name)
        out[name] = str(tile_dem(tmp, data, 65, nodata=nd))
    return out


def _drawn(make_renderer, path: str, lod: str, holes: bool = False) -> tuple[int, np.ndarray]:
    r = make_renderer(path, size=SIZE)
    cam = overview_camera(r.store, SIZE)
    st = get_strategy(lod, r)
    sel, _ = st.select(cam, 1.0)
    st.draw(cam, sel, clear=CLEAR, holes=holes)
    return r.drawn_pixels(), r.image()


@pytest.mark.parametrize("lod", strategy_names())
@pytest.mark.parametrize("dem", ["checker", "columns"])
def test_no_triangle_with_a_nodata_corner_draws_a_pixel(stores, make_renderer, dem, lod):
    """Every triangle has a nodata corner: not one pixel (before: 2 to 14 pixels on the
    edges between two terrain corners). Positive control: the same triangles drawn with their
    holes (the crack check's mode) cover the view, so they are in it."""
    assert _drawn(make_renderer, stores[dem], lod)[0] == 0
    assert _drawn(make_renderer, stores[dem], lod, holes=True)[0] > 1000


@pytest.mark.parametrize("lod", strategy_names())
def test_quiet_terrain_without_nodata_is_drawn_as_with_its_holes(stores, make_renderer, lod):
    """Quiet case: without nodata no vertex is clipped, so the image is the same pixel for
    pixel whether masked triangles are clipped or drawn; with a nodata hole only the hole's
    triangles differ (the terrain around it is drawn)."""
    n, img = _drawn(make_renderer, stores["plain"], lod)
    n_h, img_h = _drawn(make_renderer, stores["plain"], lod, holes=True)
    assert n > 1000 and n == n_h and np.array_equal(img, img_h)
    n, _ = _drawn(make_renderer, stores["hole"], lod)
    n_h, _ = _drawn(make_renderer, stores["hole"], lod, holes=True)
    assert 1000 < n < n_h


def test_terrain_cells(stores):
    from tiler.store import open_store

    assert not terrain_cells(open_store(stores["checker"]))
    assert not terrain_cells(open_store(stores["columns"]))
    assert terrain_cells(open_store(stores["hole"])) and terrain_cells(open_store(stores["plain"]))


@pytest.mark.parametrize("lod", strategy_names())
def test_render_of_a_dem_without_a_whole_cell_fails_naming_it(stores, tmp_path, lod):
    """``render`` wrote a near-empty sky PNG (``drawn_px`` 1..14) with exit 0; now exit 2
    naming the DEM's missing whole cells, and no file. Quiet case: the DEM with a hole renders."""
    out = tmp_path / "v.png"
    args = ["--size", "128x96", "--lod", lod, "-o", str(out), "--json"]
    res = runner.invoke(app, ["render", stores["checker"], *args])
    assert res.exit_code == 2, res.output
    assert "no cell of the DEM has four terrain corners" in res.output, res.output
    assert "too sparse to draw" in res.output and "too far" not in res.output
    assert not out.exists()
    res = runner.invoke(app, ["render", stores["hole"], *args])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output.splitlines()[-1])["drawn_px"] > 1000


def test_tradeoff_of_a_dem_without_a_whole_cell_names_why(stores):
    """``tradeoff`` of such a DEM said "it holds no terrain sample, or the DEM is smaller than a
    pixel from there"; it now names the missing whole cells. Quiet case: the DEM with a hole
    measures."""
    args = ["--size", "96x72", "--taus", "2", "--repeats", "1"]
    res = runner.invoke(app, ["tradeoff", stores["checker"], *args])
    assert res.exit_code == 2, res.output
    assert "no cell of the DEM has four terrain corners" in res.output, res.output
    assert "smaller than a pixel" not in res.output
    res = runner.invoke(app, ["tradeoff", stores["hole"], *args])
    assert res.exit_code == 0, res.output
