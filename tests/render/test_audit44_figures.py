"""Audit 44 (measurement figures): a figure that measured nothing reads "not measured", not a
perfect 0, and a table never rounds a share to a reading it is not.

Seen by the audit: ``terrastream tradeoff --nodata-rule gap`` on a DEM whose coarse levels have
no drawable triangle (terrain on rows 1 and 2 of every 4, so every coarser vertex row is nodata)
drew no in-view sample at τ = 8 and printed ``max px 0.00  p99 px 0.00`` (JSON
``max_screen_error_px: 0.0``, ``samples_in_view: 0``); and on Longyearbyen under ``gap``
``nodata_covered`` = 7.8e-05 (holes drawn over) printed as ``0.0%``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from gltools import tile_dem
from typer.testing import CliRunner

from cli.main import app
from render import measure
from render.coverage import percent
from render.pipeline import TradeoffRow, format_row

runner = CliRunner()


# -- error figures of an empty measurement (pure) -----------------------------------------------


def test_no_measured_sample_is_not_an_error_of_zero():
    st = measure.error_stats(np.zeros(0))
    assert st.samples == 0
    assert math.isnan(st.max_px) and math.isnan(st.p99_px) and math.isnan(st.mean_px)


def test_measured_samples_keep_their_figures():
    st = measure.error_stats(np.array([0.0, 0.5, 2.0]))
    assert (st.samples, st.max_px, st.mean_px) == (3, 2.0, pytest.approx(2.5 / 3))
    zero = measure.error_stats(np.zeros(5))  # a measured perfect surface reads 0
    assert (zero.samples, zero.max_px, zero.p99_px, zero.mean_px) == (5, 0.0, 0.0, 0.0)


# -- shares in the tables (pure) ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("share", "text"),
    [(0.0, "0.0%"), (1.0, "100.0%"), (0.5, "50.0%"), (0.9994, "99.9%"), (0.0005, "0.1%"),
     (7.8e-05, "<0.1%"), (1e-12, "<0.1%"), (0.99996, ">99.9%"), (1 - 1e-12, ">99.9%")],
)  # fmt: skip
def test_a_share_is_never_rounded_to_none_or_all(share, text):
    assert percent(share) == text


def _row(**kw) -> TradeoffRow:
    base = dict(
        tau=1.0, metric="qiu", triangles=10, patches=1, selection_ms=1.0, frame_ms=1.0,
        reference_frame_ms=1.0, reference_triangles=20, max_screen_error_px=0.5,
        p99_screen_error_px=0.4, mean_screen_error_px=0.1, samples_in_view=100, psnr_db=40.0,
        changed_share=0.01, crack_pixels=0, resident_bytes=0, loaded_bytes=0, gpu_bytes=0,
        clamped=0,
    )  # fmt: skip
    base.update(kw)
    return TradeoffRow(**base)


def test_the_tradeoff_table_shows_holes_drawn_over_and_terrain_dropped():
    """Positive control: 14 of 178,413 nodata samples drawn over (Longyearbyen, ``gap``) and
    26 of 66,049 terrain samples dropped show; the quiet row reads 100.0 % and 0.0 %."""
    fired = format_row(_row(terrain_covered=1 - 26 / 66049, nodata_covered=14 / 178413))
    assert ">99.9%" in fired and "<0.1%" in fired and "100.0%" not in fired
    quiet = format_row(_row(terrain_covered=1.0, nodata_covered=0.0))
    assert "100.0%" in quiet and "0.0%" in quiet and "<" not in quiet and ">" not in quiet
    from render.pipeline import TABLE_HEADER

    # the columns stay aligned with the header
    assert len(fired) == len(quiet) == len(TABLE_HEADER)


# -- end to end: a sweep whose LOD surface draws no sample in view -----------------------------


@pytest.fixture(scope="module")
def striped(tmp_path_factory):
    """A 257² DEM (30 m cells, blocks of 65²) with terrain on rows 1 and 2 of every 4 only: the
    full-resolution mesh draws a cell row between them, but every level-1-or-coarser vertex row
    (even rows: 0 or 2 mod 4, never both valid beside each other) leaves no drawable triangle."""
    n = 257
    r, c = np.mgrid[0:n, 0:n]
    dem = 800 + 40 * np.sin(c / 9.0) * np.cos(r / 7.0)
    valid = (r % 4 == 1) | (r % 4 == 2)
    d = tmp_path_factory.mktemp("stripes")
    tile_dem(d, np.where(valid, np.rint(dem), -9999).astype(np.int16), 65, nodata=-9999)
    return d


@pytest.mark.gl
def test_a_surface_that_draws_no_sample_in_view_has_no_error_figure(striped):
    """Positive control: under ``gap`` at τ = 8 from the default view at 64x48 the drawn
    surface covers none of the in-view terrain, so nothing is measured: the JSON's errors are
    null and the table's ``nan``, not a perfect 0.00; the quiet case (``full``, every mixed node
    at full resolution) measures every sample (0 px, since it is the reference)."""
    out = striped / "t.json"
    res = runner.invoke(app, ["tradeoff", str(striped / "s.zarr"), "--size", "64x48",
                              "--taus", "8", "--repeats", "1", "--nodata-rule", "gap",
                              "--json", str(out), "--overwrite"])  # fmt: skip
    assert res.exit_code == 0, res.output
    row = json.loads(out.read_text())[0]
    assert row["samples_in_view"] == 0 and row["terrain_covered"] == 0.0
    assert row["terrain_in_view"] > 1000
    assert row["max_screen_error_px"] is None and row["p99_screen_error_px"] is None
    assert row["mean_screen_error_px"] is None
    line = [ln for ln in res.output.splitlines() if ln.split()[:2] == ["8", "qiu"]][0]
    assert line.split()[6:8] == ["nan", "nan"]  # max px, p99 px

    res = runner.invoke(app, ["tradeoff", str(striped / "s.zarr"), "--size", "64x48",
                              "--taus", "8", "--repeats", "1", "--nodata-rule", "full",
                              "--json", str(out), "--overwrite"])  # fmt: skip
    assert res.exit_code == 0, res.output
    row = json.loads(out.read_text())[0]
    assert row["samples_in_view"] == row["terrain_in_view"] > 1000
    assert row["max_screen_error_px"] == 0.0 and row["terrain_covered"] == 1.0


# -- crack pixels on the image's edge ----------------------------------------------------------


@pytest.fixture(scope="module")
def nadir_view(tmp_path_factory):
    """A rough 257² DEM (blocks of 65², every block on the GPU at full resolution) seen straight
    down from 1.2 km above it, terrain filling the whole 128x96 image, with the reference's
    selection and footprint."""
    from gltools import make_context, rough

    from render.renderer import CLEAR, RenderConfig, TerrainRenderer
    from streamer.camera import Camera
    from tiler.store import open_store

    s = open_store(tile_dem(tmp_path_factory.mktemp("nadir"), rough(257, 5, amp=20.0), 65))
    r = TerrainRenderer(s, RenderConfig(size=(128, 96), patch_log2=2), ctx=make_context())
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    x0, y0, x1, _ = r.grid.extent
    cam = Camera(((x0 + x1) / 2, y0 + 3800, 2000), pitch=-90, viewport=(128, 96), near=5.0,
                 far=1e5)  # fmt: skip
    ref, _ = r.select(cam, 0.0, full=True)
    r.draw(cam, ref, clear=CLEAR)
    footprint = ~measure.is_clear(r.image(), CLEAR)
    assert footprint.all()  # terrain everywhere: only the image border can reach a clear pixel
    yield r, cam, ref, footprint
    r.close()


@pytest.mark.gl
@pytest.mark.parametrize("name", ["qiu", "jung-han"])
def test_cracks_running_off_the_image_edge_are_counted(nadir_view, name):
    """Positive control: stitching off, every clear pixel of the view looks through a gap in
    the drawn mesh (terrain fills the image), and some lie on the image's edge, joined to it
    through clear pixels; the count from the camera has every one of them (it left out the
    ones the border reaches: jung-han 156 of 234, geometry-splitting 239 of 242). Quiet case:
    stitching on, 0."""
    from render import cracks
    from render.pipeline import drawn_cracks
    from render.renderer import CLEAR
    from render.strategies import get_strategy

    r, cam, ref, footprint = nadir_view
    st = get_strategy(name, r)
    st.stitching = False
    sel, _ = st.select(cam, 8.0)
    tri, h = st.triangles(cam, sel)
    here, _ = drawn_cracks(r, st, cam, sel, ref, footprint, (tri, h))
    st.draw(cam, sel, clear=CLEAR)
    clear = measure.is_clear(r.image(), CLEAR)
    rows, cols = np.nonzero(clear)
    through = cracks.rays_below(r.grid, cam, tri, h, np.c_[rows, cols])
    edge = (rows == 0) | (rows == clear.shape[0] - 1) | (cols == 0) | (cols == clear.shape[1] - 1)
    assert (through & edge).any()  # cracks reach the image's edge
    assert here == int(through.sum()) > 50
    if name == "jung-han":  # what the border hid (78 pixels; 1 for qiu, 3 for the other)
        assert here > measure.crack_pixels(r.image(), footprint, CLEAR) + 50

    st.stitching = True
    sel, _ = st.select(cam, 8.0)
    assert drawn_cracks(r, st, cam, sel, ref, footprint) == (0, 0)


# -- terrain samples the near plane clips ------------------------------------------------------


@pytest.fixture(scope="module")
def slope(tmp_path_factory):
    """A sloping 65² DEM (10 m cells, blocks of 33²), every block on the GPU."""
    from gltools import make_context

    from render.renderer import RenderConfig, TerrainRenderer
    from tiler.store import open_store

    dem = 300.0 + np.add.outer(np.arange(65), np.arange(65)).astype(np.float32)
    s = open_store(tile_dem(tmp_path_factory.mktemp("slope"), dem, 33))
    r = TerrainRenderer(s, RenderConfig(size=(128, 96), patch_log2=2), ctx=make_context())
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield r
    r.close()


@pytest.mark.gl
def test_samples_nearer_than_the_near_plane_are_all_counted(slope):
    """Positive control: with a 1,400 m near plane the pipeline's reference (selected with
    that camera) culls the nodes wholly nearer than it, and the clipped count read 278 of the
    1,327 clipped samples; every one is counted now, so the in-view and the clipped samples add
    up to the in-view samples of the same camera with a 5 m near plane (quiet: 0 clipped)."""
    from dataclasses import replace

    from render import coverage
    from render.pipeline import tradeoff
    from streamer.camera import Camera

    r = slope
    g = r.grid
    pos = (g.x0 + 32 * g.dx, g.y0 - 64 * g.dy - 600.0, 900.0)  # south, looking north
    open_cam = Camera(pos, pitch=-30.0, viewport=(128, 96), near=5.0, far=5e4)
    clip_cam = replace(open_cam, near=1400.0)
    a, b = (tradeoff(r.store, c, [1.0], renderer=r, repeats=1)[0] for c in (open_cam, clip_cam))
    assert a.near_clipped_samples == 0 and a.terrain_in_view > 3000
    assert b.near_clipped_samples > 1000
    assert b.terrain_in_view + b.near_clipped_samples == a.terrain_in_view
    assert coverage.near_clipped_samples(r.store, clip_cam) == b.near_clipped_samples


def test_the_compare_table_and_front_do_not_hide_holes_or_crown_an_empty_row():
    """``compare``'s table rounded 4 undrawn terrain samples of 200,000 to ``100.0%``, and a
    row with nothing measured (NaN error) would lead the Pareto front at "0 px". The controls:
    exact shares print as before, and measured rows make the front."""
    from render.strategies.compare import pareto_front, table_cells

    row = {
        "strategy": "qiu", "tau": 1.0, "triangles": 10, "max_screen_error_px": 0.5,
        "p99_screen_error_px": 0.4, "mean_screen_error_px": 0.1, "crack_pixels": 0,
        "crack_pixels_above": 0, "open_edges": 0, "gap_edges": 0, "max_gap_m": 0.0,
        "terrain_covered": 1 - 4 / 200_000, "nodata_covered": 3 / 200_000,
        "near_clipped_samples": 0, "fly_triangles": 10.0, "fly_cpu_ms": 1.0,
        "fly_gpu_ms": 1.0, "used_bytes": 0, "own_gpu_bytes": 0,
    }  # fmt: skip
    cells = table_cells(row)
    assert (cells["terrain"], cells["nodata"]) == (">99.9%", "<0.1%"), cells
    cells = table_cells(row | {"terrain_covered": 1.0, "nodata_covered": 0.0})
    assert (cells["terrain"], cells["nodata"]) == ("100.0%", "0.0%"), cells
    assert pareto_front([(math.nan, 5.0), (1.0, 20.0), (2.0, 10.0)]) == [(1.0, 20.0), (2.0, 10.0)]
