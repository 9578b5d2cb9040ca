"""Many sources, one store: a mosaic read window by window equals the single-file DEM."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import fractal, shared_file, write_dem
from rasterio.windows import Window

from tiler.errors import SourceError
from tiler.mosaic import MosaicReader, plan_mosaic
from tiler.source import read_source_list
from tiler.tile import TileOptions, tile

CELL = 30.0
X0, Y0 = 500000.0, 5000000.0


def cut(tmp_path, data, rows, cols, name="t", nodata=None, order=None):
    """Write the pieces ``data[r0:r1, c0:c1]`` for every (rows x cols) pair as GeoTIFFs."""
    paths = []
    for i, (r0, r1) in enumerate(rows):
        for j, (c0, c1) in enumerate(cols):
            p = write_dem(
                tmp_path / f"{name}_{i}_{j}.tif",
                np.ascontiguousarray(data[r0:r1, c0:c1]),
                origin=(X0 + c0 * CELL, Y0 - r0 * CELL),
                cell=CELL,
                nodata=nodata,
            )
            paths.append(p)
    if order is not None:
        paths = [paths[i] for i in order]
    return paths


def assert_same_store(a, b):
    """Two stores hold the same DEM: shape, transform, CRS, every level of every block, mask."""
    assert (a.meta.height, a.meta.width) == (b.meta.height, b.meta.width)
    assert a.meta.geotransform == pytest.approx(b.meta.geotransform, rel=1e-12)
    assert a.meta.crs_wkt == b.meta.crs_wkt
    np.testing.assert_array_equal(a.index.exists, b.index.exists)
    for blk in a.grid.blocks():
        np.testing.assert_array_equal(a.read_mask(blk), b.read_mask(blk))
        for level in range(a.k + 1):
            np.testing.assert_array_equal(a.read_block(blk, level), b.read_block(blk, level))
        np.testing.assert_array_equal(a.read_errors(blk)["qiu"][-1], b.read_errors(blk)["qiu"][-1])


# a 3x3 grid of pieces: shared edge rows (SRTM-like), wider overlaps, and one exact abutment
ROWS = [(0, 61), (60, 131), (120, 161)]
COLS = [(0, 71), (66, 140), (139, 181)]


@pytest.mark.parametrize("executor", ["threads", "processes"])
def test_3x3_overlapping_tiles_equal_single_file(tmp_path, executor):
    data = fractal((161, 181), seed=3)
    whole = write_dem(tmp_path / "whole.tif", data, origin=(X0, Y0), cell=CELL)
    order = [4, 0, 8, 2, 6, 1, 3, 5, 7]  # any order: overlaps hold identical samples
    pieces = cut(tmp_path, data, ROWS, COLS, order=order)
    opts = TileOptions(block_size=33, workers=2, executor=executor)
    ref = tile(whole, tmp_path / "whole.zarr", opts)
    got = tile(pieces, tmp_path / "mosaic.zarr", opts)
    assert got.meta.nodata is None  # the pieces cover the grid: no nodata invented
    assert got.meta.extra["mosaic"] == {"count": 9, "overlap_rule": "first-valid"}
    assert got.meta.source["name"].endswith(" + 8 more")
    assert len(got.meta.source["paths"]) == 9
    assert_same_store(got, ref)


def test_reader_windows_equal_the_array_and_open_few_files(tmp_path):
    data = fractal((161, 181), seed=4)
    pieces = cut(tmp_path, data, ROWS, COLS)
    spec = plan_mosaic(pieces)
    assert (spec.height, spec.width) == data.shape
    rng = np.random.default_rng(0)
    with MosaicReader(spec, max_open=2) as reader:
        for _ in range(40):
            r0, c0 = int(rng.integers(0, 150)), int(rng.integers(0, 170))
            h, w = int(rng.integers(1, 161 - r0)), int(rng.integers(1, 181 - c0))
            got = reader.read(1, Window(c0, r0, w, h))
            np.testing.assert_array_equal(got, data[r0 : r0 + h, c0 : c0 + w])
            assert len(reader._open) <= 2  # bounded whatever the number of files
        # a window inside one piece touches only that piece
        assert reader.sources_for(10, 10, 20, 20) == [0]
        assert reader.sources_for(60, 66, 1, 1) == [0, 1, 3, 4]  # the shared corner


def test_overlap_rule_first_valid_wins_and_nodata_is_filled(tmp_path):
    a = np.full((20, 20), 100, np.int16)
    a[5, 5] = -9999  # a hole in the first source
    b = np.full((20, 20), 200, np.int16)
    pa = write_dem(tmp_path / "a.tif", a, nodata=-9999, origin=(X0, Y0), cell=CELL)
    pb = write_dem(tmp_path / "b.tif", b, nodata=-9999, origin=(X0 + 10 * CELL, Y0), cell=CELL)
    spec = plan_mosaic([pa, pb])
    with MosaicReader(spec) as r:
        got = r.read_window(0, 0, 20, 30)
    hole = np.zeros((20, 20), bool)
    hole[5, 5] = True
    assert (got[:, :20][~hole] == 100).all()  # a wins over its own extent
    assert got[5, 5] == -9999  # a's hole, which b does not cover, stays nodata
    assert (got[:, 20:] == 200).all()
    spec = plan_mosaic([pb, pa])  # the other order: b wins on the overlap
    with MosaicReader(spec) as r:
        got = r.read_window(0, 0, 20, 30)
    assert (got[:, 10:] == 200).all() and (got[:, :10][~hole[:, :10]] == 100).all()
    # a hole in the first source is filled by the second where it covers it
    a2 = a.copy()
    a2[5, 15] = -9999
    pa2 = write_dem(tmp_path / "a2.tif", a2, nodata=-9999, origin=(X0, Y0), cell=CELL)
    with MosaicReader(plan_mosaic([pa2, pb])) as r:
        got = r.read_window(0, 0, 20, 30)
    assert got[5, 15] == 200 and got[5, 5] == -9999


def test_gaps_become_nodata_and_are_masked(tmp_path):
    data = fractal((40, 40), seed=5)
    pieces = cut(tmp_path, data, [(0, 20), (20, 40)], [(0, 20), (20, 40)])
    store = tile(pieces[:3], tmp_path / "gap.zarr", TileOptions(block_size=17))
    assert store.meta.nodata == float(np.iinfo(np.int16).min)  # invented for the gap
    mask = np.zeros((49, 49), bool)
    for br, bc in store.grid.blocks():
        r0, c0 = br * 16, bc * 16
        mask[r0 : r0 + 17, c0 : c0 + 17] |= store.read_mask((br, bc))
    assert not mask[20:40, 20:40].any()
    assert mask[:20, :40].all() and mask[:40, :20].all()


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"crs": "EPSG:32632"}, "different CRSs"),
        ({"cell": 31.0}, "different pixel sizes"),
        ({"origin": (X0 + 20 * CELL + 7.0, Y0)}, "not on the pixel grid"),
    ],
    ids=["crs", "pixel-size", "misaligned"],
)
def test_incompatible_sources_are_refused(tmp_path, change, needle):
    a = write_dem(tmp_path / "a.tif", fractal((20, 20)), origin=(X0, Y0), cell=CELL)
    kw = {"origin": (X0 + 20 * CELL, Y0), "cell": CELL, **change}
    b = write_dem(tmp_path / "b.tif", fractal((20, 20), seed=1), **kw)
    with pytest.raises(SourceError, match=needle) as e:
        plan_mosaic([a, b])
    assert "b.tif" in str(e.value)


def test_source_list_file(tmp_path):
    data = fractal((40, 40), seed=6)
    pieces = cut(tmp_path, data, [(0, 21), (20, 40)], [(0, 40)])
    lst = tmp_path / "tiles.txt"
    lst.write_text(f"# two tiles\n{pieces[0].name}\n\n{pieces[1]}\n")
    assert read_source_list(lst) == [str(pieces[0]), str(pieces[1])]
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    with pytest.raises(SourceError, match="names no rasters"):
        read_source_list(empty)


def _write_piece(path, ds, r0, r1, c0, c1):
    win = Window(c0, r0, c1 - c0, r1 - r0)
    profile = dict(ds.profile, driver="GTiff", width=c1 - c0, height=r1 - r0)
    profile["transform"] = ds.window_transform(win)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(ds.read(1, window=win), 1)
    return path


@pytest.mark.shared_data
def test_srtm_pieces_with_shared_and_wide_overlaps_equal_the_tile(tmp_path):
    src = shared_file("N44W072.hgt")
    with rasterio.open(src) as ds:
        # adjacent tiles share their edge row/column like SRTM; the right half overlaps by 100
        parts = [
            _write_piece(tmp_path / "nw.tif", ds, 0, 601, 0, 651),
            _write_piece(tmp_path / "sw.tif", ds, 600, 1201, 0, 651),
            _write_piece(tmp_path / "e.tif", ds, 0, 1201, 550, 1201),
        ]
    opts = TileOptions(block_size=257, workers=2)
    whole = tile(src, tmp_path / "whole.zarr", opts)
    mosaic = tile(parts[::-1], tmp_path / "mosaic.zarr", opts)
    assert_same_store(mosaic, whole)


def test_reprojected_mosaic_matches_the_reprojected_single_file(tmp_path):
    """With a target CRS each tile is warped on its own; inside the tiles' sample hulls the
    bilinear kernel only sees that tile's samples, so the result is the single file's up to
    integer rounding ties (the transforms differ by < WARP_TOLERANCE pixels)."""
    from tiler.accuracy import store_array

    deg = 1 / 120
    data = fractal((121, 121), seed=14)
    single = write_dem(tmp_path / "one.tif", data, crs="EPSG:4326", origin=(11.0, 50.0), cell=deg)
    parts = []
    for i, (r0, r1) in enumerate([(0, 61), (60, 121)]):
        for j, (c0, c1) in enumerate([(0, 61), (60, 121)]):
            parts.append(
                write_dem(
                    tmp_path / f"p{i}{j}.tif",
                    np.ascontiguousarray(data[r0:r1, c0:c1]),
                    crs="EPSG:4326",
                    origin=(11.0 + c0 * deg, 50.0 - r0 * deg),
                    cell=deg,
                )
            )
    opts = TileOptions(block_size=65, dst_crs="auto")
    a = tile(single, tmp_path / "one.zarr", opts)
    b = tile(parts, tmp_path / "parts.zarr", opts)
    assert a.meta.geotransform == b.meta.geotransform and a.meta.crs_wkt == b.meta.crs_wkt
    ha, va = store_array(a)
    hb, vb = store_array(b)
    both = va & vb
    assert (va != vb).sum() <= 0.002 * va.sum()  # only the outer hull's chords differ
    diff = np.abs(ha - hb)[both]
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3, (diff.max(), (diff > 0).mean())


def test_sources_with_different_height_scales_are_refused(tmp_path):
    a = write_dem(tmp_path / "a.tif", fractal((20, 20)), origin=(X0, Y0), cell=CELL)
    b = write_dem(tmp_path / "b.tif", fractal((20, 20)), origin=(X0 + 19 * CELL, Y0), cell=CELL)
    with rasterio.open(b, "r+") as ds:
        ds.units = ("m",)  # metres spelled out: the same as no unit
    plan_mosaic([a, b])
    with rasterio.open(b, "r+") as ds:
        ds.scales = (0.1,)
    with pytest.raises(SourceError, match="disagree on height scale"):
        plan_mosaic([a, b])


def test_a_hundred_tiles_from_a_list_equal_the_single_file(tmp_path):
    """Many small SRTM-like tiles (shared edges) listed in a file: one store, equal to the
    single file; a reader never holds more than MAX_OPEN of them open."""
    from tiler.mosaic import MAX_OPEN

    data = fractal((91, 91), seed=15)
    spans = [(9 * i, 9 * i + 10) for i in range(10)]
    pieces = cut(tmp_path, data, spans, spans)
    assert len(pieces) == 100
    lst = tmp_path / "tiles.txt"
    lst.write_text("".join(f"{p.name}\n" for p in reversed(pieces)))
    whole = write_dem(tmp_path / "whole.tif", data, origin=(X0, Y0), cell=CELL)
    opts = TileOptions(block_size=33, workers=2, executor="threads")
    ref = tile(whole, tmp_path / "whole.zarr", opts)
    got = tile(read_source_list(lst), tmp_path / "list.zarr", opts)
    assert_same_store(got, ref)
    with MosaicReader(plan_mosaic(read_source_list(lst))) as reader:
        np.testing.assert_array_equal(reader.read_window(0, 0, 91, 91), data)
        assert len(reader._open) <= MAX_OPEN < 100


def _side_by_side(tmp_path, b_void):
    """Two int16 tiles side by side: A (nodata -32768, a void) and B (nodata -9999, its own
    void at ``b_void``). Returns their paths and the expected mosaic (NaN: nodata)."""
    base = np.round(fractal((120, 160), seed=9) / 10).astype(np.int16) + 100
    a, b = base[:, :80].copy(), base[:, 80:].copy()
    a[10:20, 10:20] = -32768
    b[b_void] = -9999
    pa = write_dem(tmp_path / "a.tif", a, nodata=-32768)
    pb = write_dem(tmp_path / "b.tif", b, nodata=-9999, origin=(500000.0 + 80 * 30, 5e6))
    want = base.astype(float)
    want[10:20, 10:20] = np.nan
    want[:, 80:][b_void] = np.nan
    return pa, pb, want


@pytest.mark.parametrize("block_size", [33, 257])
def test_a_later_sources_own_nodata_is_nodata_in_every_block(tmp_path, block_size):
    """B's voids (its nodata -9999, not A's -32768) are nodata whatever the block size; with
    blocks inside B alone they were stored as -9999 m heights (the single-source shortcut kept
    B's raw samples), and verify --source agreed."""
    from tiler.verify import verify_store

    pa, pb, want = _side_by_side(tmp_path, (slice(40, 80), slice(30, 70)))
    s = tile([pa, pb], tmp_path / "m.zarr", TileOptions(block_size=block_size))
    got = np.full(want.shape, np.nan)
    for br, bc in s.blocks():
        r0, c0, h, w = s.grid.block_window(br, bc)
        g = s.read_block((br, bc), extent=(h, w)).astype(float)
        g[~s.read_mask((br, bc))[:h, :w]] = np.nan
        got[r0 : r0 + h, c0 : c0 + w] = g
    np.testing.assert_array_equal(got, want)
    assert s.meta.extra["value_range"][0] >= 0  # (-9999 was the minimum)
    assert verify_store(tmp_path / "m.zarr", source=[pa, pb]).ok


def test_a_valid_sample_equal_to_the_mosaics_nodata_is_refused(tmp_path):
    """B declares no nodata and has valid -9999 m samples... where A's nodata is -9999: they
    would read as nodata. Refused, naming B and the value (they vanished before)."""
    base = np.round(fractal((120, 160), seed=9) / 10).astype(np.int16) + 100
    a, b = base[:, :80].copy(), base[:, 80:].copy()
    a[10:20, 10:20] = -9999
    b[:5, :5] = -9999  # valid heights in B (it declares no nodata)
    pa = write_dem(tmp_path / "a.tif", a, nodata=-9999)
    pb = write_dem(tmp_path / "b.tif", b, nodata=None, origin=(500000.0 + 80 * 30, 5e6))
    with pytest.raises(SourceError, match=r"'.*b\.tif' has valid samples equal to -9999, the "):
        tile([pa, pb], tmp_path / "m.zarr", TileOptions(block_size=33))
