"""Numerical extremes (the numerics audit): no crack "from above" on a watertight mesh at a
wide FOV, chunk-tessellation-gpu's traversal at a tau beyond float32, a non-finite tau refused,
and a camera on or under the ground warned about (and named when it sees no terrain)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import cracks, pipeline
from render.errors import EmptyViewError, SelectionError
from render.renderer import RenderConfig, TerrainRenderer
from render.select import check_tau
from render.strategies import get_strategy
from render.views import make_camera
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)


def _all_rays(grid, camera, tri, h, pixels, chunk=0):
    """``cracks.rays_below`` as the old count had it: every enclosed clear pixel a crack."""
    return np.ones(len(np.asarray(pixels).reshape(-1, 2)), bool)


@pytest.fixture(scope="module")
def synth257(tmp_path_factory):
    """The audit's plain 257² synthetic DEM (``terrastream synth --size 257 --seed 3``)."""
    from tiler.synth import synth_dem
    from tiler.tile import TileOptions, tile

    tmp = tmp_path_factory.mktemp("synth257")
    synth_dem(tmp / "s.tif", 257, seed=3)
    tile(tmp / "s.tif", tmp / "s.zarr", TileOptions(block_size=129, workers=1))
    return open_store(tmp / "s.zarr")


# -- 2. cracks from above: a ray past a ridge is no crack -------------------------------------


@pytest.mark.parametrize("fov", [120.0, 170.0])
def test_no_crack_from_above_on_a_watertight_mesh_at_a_wide_fov(synth257, fov, monkeypatch):
    """qiu at tau 2 on the overview: watertight (no open edge), yet the wide-angle picture from
    above folds the relief, and a ray passing over a ridge leaves the DEM past its edge: an
    enclosed clear pixel that is no crack. The ray test leaves it out; the control, every
    enclosed clear pixel counted (the old figure), reads it."""
    cam = make_camera(synth257, SIZE, fov=fov)
    row = pipeline.tradeoff(synth257, cam, [2.0], repeats=1, lod="qiu")[0]
    assert (row.open_edges, row.gap_edges, row.terrain_covered) == (0, 0, 1.0)
    assert row.crack_pixels_above == 0
    monkeypatch.setattr(cracks, "rays_below", _all_rays)
    old = pipeline.tradeoff(synth257, cam, [2.0], repeats=1, lod="qiu")[0]
    assert old.crack_pixels_above > 0


def test_rays_below_tells_a_gap_from_a_ray_past_the_edge():
    """Two squares 20 m wide side by side, the west at 0 m, the east at 50 m, not joined (a gap
    along their common edge), seen straight down from 100 m above the west one: a ray reaching
    the common edge below 50 m passes under the east square (through the gap); one landing on
    the west square goes below it; one leaving past the west edge never does."""
    from tiler.grid import BlockGrid

    grid = BlockGrid(height=65, width=65, k=6, x0=0.0, y0=640.0, dx=10.0, dy=10.0)
    sq = np.array([[[0, 0], [2, 0], [2, 2]], [[0, 0], [2, 2], [0, 2]]])
    tri = np.concatenate([sq, sq + [2, 0]])
    h = np.array([[0.0] * 3, [0.0] * 3, [50.0] * 3, [50.0] * 3])
    cam = Camera((10.0, 630.0, 100.0), pitch=-90.0, fov_y=60.0, viewport=(64, 64), near=1.0)
    pixels = np.array([[32, 40], [32, 28], [32, 20], [32, 0]])  # gap, on, past, past the edge
    assert cracks.rays_below(grid, cam, tri, h, pixels).tolist() == [True, True, False, False]
    assert cracks.rays_below(grid, cam, tri, h, pixels, chunk=1).tolist() == [True, True, False,
                                                                              False]  # fmt: skip


# -- 3. chunk-tessellation-gpu at a tau beyond float32 ---------------------------------------


@pytest.fixture(scope="module")
def holed(tmp_path_factory):
    """A rough 129² DEM with a nodata disc in sight: mixed nodes carry the error inf."""
    dem = rough(129, 3).astype(np.float32)
    yy, xx = np.mgrid[:129, :129]
    dem[(yy - 70) ** 2 + (xx - 60) ** 2 < 15**2] = np.nan
    s = open_store(tile_dem(tmp_path_factory.mktemp("holed"), dem, 33, nodata=np.nan))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield r
    r.close()


def _chunks(p):
    o = np.lexsort((p.col, p.row, p.depth, p.block))
    return {f: getattr(p, f)[o] for f in ("block", "depth", "row", "col", "level", "snap")}


@pytest.mark.parametrize("tau", [1.0, 1e30, 1e39, 1e300])
def test_gpu_traversal_refines_mixed_nodes_at_any_finite_tau(holed, tau):
    """The GPU's float32 tau uniform: 1e39 was +inf, and ``!(inf <= inf)`` stopped splitting
    mixed (terrain + nodata) nodes, so terrain beside the hole was dropped. Now the GPU
    selection is its CPU twin's at every finite tau, and a huge tau keeps the mixed nodes
    refined as 1e30 does."""
    cam = Camera.look_at((500015 + 600, 5000000 - 15 - 4200, 1600.0), (500015 + 1900, 4998100,
                         700.0), viewport=SIZE, near=5.0)  # fmt: skip
    st = get_strategy("chunk-tessellation-gpu", holed, chunk_log2=2)
    sel, _ = st.select(cam, tau)
    got, want = _chunks(st.patches(sel)), _chunks(st.select_twin(cam, tau))
    for f, v in want.items():
        np.testing.assert_array_equal(got[f], v, err_msg=f)
    if tau >= 1e30:
        base = _chunks(st.select_twin(cam, 1e30))
        assert all(np.array_equal(got[f], base[f]) for f in base)
        assert got["depth"].max() > got["depth"].min()  # mixed nodes split down


# -- 4. tau must be finite -------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.inf, -1.0, math.nan, "x"])
def test_check_tau_refuses_non_finite_and_negative_values(bad):
    with pytest.raises(SelectionError, match="tau") as exc:
        check_tau(bad)
    assert repr(bad) in str(exc.value) or str(bad) in str(exc.value)


@pytest.mark.parametrize("good", [0.0, 1, 2.5, 1e300])
def test_check_tau_takes_finite_values(good):
    assert check_tau(good) == float(good)


def test_every_strategy_refuses_tau_inf_by_name(holed):
    cam = Camera((500015 + 1900, 5000000 - 15 - 3500, 1500.0), pitch=-40.0, viewport=SIZE)
    for name in ("qiu", "chunk-tessellation", "chunk-tessellation-gpu", "geometry-splitting",
                 "jung-han", "seamless-patches"):  # fmt: skip
        st = get_strategy(name, holed)
        with pytest.raises(SelectionError, match="inf"):
            st.select(cam, math.inf)
        st.select(cam, 1e300)  # the largest finite taus are taken


# -- 1. a camera on the ground: the empty view says why ---------------------------------------


def test_a_view_from_on_the_ground_names_the_camera_not_the_distance(tmp_path):
    """A camera exactly on a flat DEM sees nothing (its 1 cm near plane clips the ground): the
    "no terrain pixel" error named the DEM too far away; it names the camera on the ground. The
    control, 1 m above it, measures a row."""
    s = open_store(tile_dem(tmp_path, np.zeros((65, 65), np.int16), 33))
    x0, y0, x1, y1 = s.grid.extent
    pos = f"{(x0 + x1) / 2},{(y0 + y1) / 2}"
    cam = make_camera(s, SIZE, position=f"{pos},0", yaw=0.0, pitch=-10.0)
    with pytest.raises(EmptyViewError, match="the camera is on the terrain under it") as exc:
        pipeline.tradeoff(s, cam, [1.0], repeats=1)
    assert "near plane clips the ground" in str(exc.value)
    assert "smaller than a pixel" not in str(exc.value)
    cam = make_camera(s, SIZE, position=f"{pos},1", yaw=0.0, pitch=-10.0)
    (row,) = pipeline.tradeoff(s, cam, [1.0], repeats=1)
    assert row.terrain_covered == 1.0


def test_render_from_on_the_ground_names_the_camera(tmp_path):
    """``render`` of the same view said "the DEM is too far from the camera to be seen; move
    the camera closer"; it names the camera on the ground. The control: 1 m above, a PNG."""
    from typer.testing import CliRunner

    from cli.main import app

    p = tile_dem(tmp_path, np.zeros((65, 65), np.int16), 33)
    x0, y0, x1, y1 = open_store(p).grid.extent
    pos = f"{(x0 + x1) / 2},{(y0 + y1) / 2}"
    base = ["render", str(p), "--size", "96x64", "--yaw", "0", "--pitch", "-10"]
    res = CliRunner().invoke(app, [*base, "--camera", f"{pos},0", "-o", str(tmp_path / "a.png")])
    assert res.exit_code == 2, res.output
    assert "the camera is on the terrain" in res.output and "too far" not in res.output
    res = CliRunner().invoke(app, [*base, "--camera", f"{pos},1", "-o", str(tmp_path / "b.png")])
    assert res.exit_code == 0 and (tmp_path / "b.png").is_file(), res.output
