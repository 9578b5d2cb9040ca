"""Reprojected tiling against GDAL's own warp of each whole source: sources past or on both
sides of the antimeridian, and mosaics of sources in different CRSs (audit 44)."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import fractal, write_dem
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.features import geometry_mask
from rasterio.transform import Affine
from rasterio.warp import reproject

from tiler.accuracy import store_array
from tiler.crs import crs_name, lonlat_union
from tiler.errors import SourceError
from tiler.mosaic import plan_mosaic, wrapped_crs
from tiler.source_header import read_info
from tiler.tile import TileOptions, tile

DEG = 1 / 30  # 2° in 61 samples


def gdal_reference(paths, store, resampling="bilinear"):
    """``(heights, valid)`` of ``rasterio.warp.reproject`` of each whole source onto the
    store's grid (first valid wins), each cut at its sample-centre hull as the store is."""
    m = store.meta
    t = Affine(*m.geotransform)
    spec = plan_mosaic(
        [str(p) for p in paths], dst_crs=m.extra["reprojection"]["requested"], resampling=resampling
    )
    assert spec.transform == tuple(m.geotransform)
    ref = np.full((m.height, m.width), np.nan)
    for path, info in zip(paths, spec.sources, strict=True):
        with rasterio.open(path) as ds:
            data = ds.read(1).astype(np.float64)
            if ds.nodata is not None:
                data[data == ds.nodata] = np.nan
            # GDAL's warp of a plain array: it finds the source's samples past ±180
            out = np.full((m.height, m.width), np.nan)
            reproject(data, out, src_transform=ds.transform, src_crs=ds.crs, dst_transform=t,
                      dst_crs=CRS.from_wkt(m.crs_wkt), resampling=Resampling[resampling],
                      src_nodata=np.nan, dst_nodata=np.nan)  # fmt: skip
        hull = [{"type": "Polygon", "coordinates": [info.hull]}]
        inside = geometry_mask(hull, out_shape=out.shape, transform=t, invert=True)
        take = np.isnan(ref) & np.isfinite(out) & inside
        ref[take] = out[take]
    return ref, np.isfinite(ref)


def assert_like_gdal(store, paths, tol=1.5):
    """The store holds GDAL's warp: the same samples valid (but for a few on the hull's
    chords) and heights within ``tol`` m (int16 rounding + the transform approximation)."""
    heights, valid = store_array(store)
    ref, ref_valid = gdal_reference(paths, store)
    assert ref_valid.sum() > 0
    lost, invented = (ref_valid & ~valid).sum(), (valid & ~ref_valid).sum()
    assert lost <= 0.002 * ref_valid.sum(), f"{lost} of {ref_valid.sum()} samples lost"
    assert invented <= 0.002 * ref_valid.sum(), f"{invented} samples invented"
    diff = np.abs(heights - ref)[valid & ref_valid]
    assert diff.max() <= tol, diff.max()


def test_lonlat_union_takes_the_short_way_round():
    assert lonlat_union([(179, -18, 180, -16), (-180, -18, -179, -16)]) == (179, -18, 181, -16)
    assert lonlat_union([(10, 0, 11, 1), (12, 2, 13, 3)]) == (10, 0, 13, 3)
    assert lonlat_union([(170, 0, -170, 1)]) == (170, 0, 190, 1)  # (transform_bounds' crossing)
    assert lonlat_union([(170, 0, -170, 1), (0, 0, 1, 1)]) == (0, 0, 190, 1)
    assert lonlat_union([(-180, 0, 180, 1)]) == (-180, 0, 180, 1)


def test_a_geographic_source_past_the_antimeridian_keeps_its_eastern_half(tmp_path):
    """A source on 179..181°E: GDAL's warper mapped the target back to -180..180, found no
    sample for 181 (read as -179) and left the eastern half nodata, exit 0. Its CRS is now
    wrapped round its centre; the store holds GDAL's warp of the whole array."""
    data = fractal((61, 61), seed=3)
    src = write_dem(tmp_path / "am.tif", data, crs="EPSG:4326", origin=(179.0, -16.0), cell=DEG)
    store = tile(src, tmp_path / "am.zarr", TileOptions(block_size=33, dst_crs="auto"))
    assert crs_name(store.meta.crs_wkt) == "EPSG:32701"
    assert_like_gdal(store, [src])
    assert wrapped_crs(read_info(str(src), 1)) is not None
    # quiet: the same DEM west of the antimeridian is read with its own CRS, and holds the same
    west = write_dem(tmp_path / "w.tif", data, crs="EPSG:4326", origin=(176.0, -16.0), cell=DEG)
    assert wrapped_crs(read_info(str(west), 1)) is None
    plain = tile(west, tmp_path / "w.zarr", TileOptions(block_size=33, dst_crs="auto"))
    assert_like_gdal(plain, [west])
    assert abs(int(store_array(plain)[1].sum()) - int(store_array(store)[1].sum())) < 0.01 * (
        store_array(plain)[1].sum()
    )


@pytest.mark.parametrize("west", [190.0, -185.0])
def test_a_geographic_source_wholly_or_partly_past_180_is_warped_whole(tmp_path, west):
    """Longitudes of a 0..360 grid (190..192) or past -180 (-185..-183) are read too."""
    data = fractal((61, 61), seed=4)
    src = write_dem(tmp_path / "s.tif", data, crs="EPSG:4326", origin=(west, -16.0), cell=DEG)
    store = tile(src, tmp_path / "s.zarr", TileOptions(block_size=33, dst_crs="auto"))
    assert_like_gdal(store, [src])


def test_a_positive_control_a_lost_half_is_caught(tmp_path):
    """The comparison fires on a store that lost samples: the eastern half read with the
    source's own CRS (what the tiler did) is far from GDAL's warp."""
    from tiler import mosaic

    data = fractal((61, 61), seed=3)
    src = write_dem(tmp_path / "am.tif", data, crs="EPSG:4326", origin=(179.0, -16.0), cell=DEG)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mosaic, "wrapped_crs", lambda info: None)
        broken = tile(src, tmp_path / "b.zarr", TileOptions(block_size=33, dst_crs="auto"))
    with pytest.raises(AssertionError, match="samples lost"):
        assert_like_gdal(broken, [src])


@pytest.mark.parametrize("dst_crs", ["auto", "EPSG:32760"])
def test_tiles_on_both_sides_of_the_antimeridian_form_one_small_grid(tmp_path, dst_crs):
    """Tiles on 179..180 and -180..-179: their union was taken in degrees (-180..180), so
    `auto` refused a 2° DEM as spanning the globe, and EPSG:32760 planned a 13822 x 9244 grid
    for 128 x 124 samples of data. The grid is now the union of the tiles on the target."""
    data = fractal((61, 61), seed=3)
    west = write_dem(tmp_path / "w.tif", np.ascontiguousarray(data[:, :31]), crs="EPSG:4326",
                     origin=(179.0, -16.0), cell=DEG)  # fmt: skip
    east = write_dem(tmp_path / "e.tif", np.ascontiguousarray(data[:, 30:]), crs="EPSG:4326",
                     origin=(-180.0, -16.0), cell=DEG)  # fmt: skip
    whole = write_dem(tmp_path / "am.tif", data, crs="EPSG:4326", origin=(179.0, -16.0),
                      cell=DEG)  # fmt: skip
    opts = TileOptions(block_size=33, dst_crs=dst_crs)
    pair = tile([west, east], tmp_path / "pair.zarr", opts)
    one = tile(whole, tmp_path / "one.zarr", opts)
    assert pair.meta.crs_wkt == one.meta.crs_wkt
    assert (pair.meta.height, pair.meta.width) == (one.meta.height, one.meta.width)
    assert pair.meta.geotransform == pytest.approx(one.meta.geotransform, abs=1e-6)
    assert_like_gdal(pair, [west, east], tol=3.0)  # (the seam's bilinear ties)


def test_sources_in_different_crss_are_warped_each_from_its_own(tmp_path):
    """A geographic tile and a UTM one: refused with "give a target CRS" even when one was
    given. Each is now warped from its own CRS onto the target's grid."""
    geo = write_dem(tmp_path / "geo.tif", fractal((61, 61), seed=5), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=1 / 60)  # fmt: skip
    utm = write_dem(tmp_path / "utm.tif", fractal((61, 61), seed=6), crs="EPSG:32632",
                    origin=(655000.0, 4990000.0), cell=600.0)  # fmt: skip
    store = tile([geo, utm], tmp_path / "mix.zarr", TileOptions(block_size=33, dst_crs="auto"))
    assert crs_name(store.meta.crs_wkt) == "EPSG:32632"
    assert store.meta.extra["source_crss"] == ["EPSG:4326", "EPSG:32632"]  # (info/tile's own)
    from tiler.info import store_info

    assert store_info(tmp_path / "mix.zarr")["source_crs"] == "EPSG:4326 + EPSG:32632"
    assert_like_gdal(store, [geo, utm], tol=3.0)
    # without a target CRS they are still refused, and the message names the option
    with pytest.raises(SourceError, match="different CRSs.*EPSG:4326.*EPSG:32632.*dst_crs"):
        tile([geo, utm], tmp_path / "no.zarr", TileOptions(block_size=33))


def test_a_mosaic_source_that_cannot_be_reprojected_is_named(tmp_path):
    geo = write_dem(tmp_path / "geo.tif", fractal((21, 21), seed=5), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=1 / 60)  # fmt: skip
    bare = write_dem(tmp_path / "bare.tif", fractal((21, 21), seed=6), crs=None)
    with pytest.raises(SourceError, match=r"bare\.tif.*has no CRS"):
        plan_mosaic([str(geo), str(bare)], dst_crs="auto")


def test_the_default_resolution_is_the_finest_sources_whatever_the_order(tmp_path):
    """A 2" tile listed after a 60" one was resampled to the 60" tile's pixel (its detail lost,
    exit 0) while listed first it kept it; the default is now the finest source's pixel, as
    gdalwarp's. Sources of one pixel size keep the grid they had (the quiet case)."""
    coarse = write_dem(tmp_path / "coarse.tif", fractal((31, 31), seed=1), crs="EPSG:4326",
                       origin=(10.0, 45.0), cell=1 / 60)  # fmt: skip
    fine = write_dem(tmp_path / "fine.tif", fractal((61, 61), seed=2), crs="EPSG:4326",
                     origin=(10.2, 44.8), cell=1 / 1800)  # fmt: skip
    one = plan_mosaic([str(coarse)], dst_crs="auto").transform[0]
    both = plan_mosaic([str(coarse), str(fine)], dst_crs="auto").transform[0]
    assert both == plan_mosaic([str(fine), str(coarse)], dst_crs="auto").transform[0]
    assert both < one / 20, (both, one)
    # quiet: two tiles of one pixel size plan the pixel of either
    twin = write_dem(tmp_path / "twin.tif", fractal((31, 31), seed=3), crs="EPSG:4326",
                     origin=(10.5, 45.0), cell=1 / 60)  # fmt: skip
    assert plan_mosaic([str(coarse), str(twin)], dst_crs="auto").transform[0] == one


def _abutting(tmp_path, seams=True):
    """``(pair, single)`` stores: 2x2 tiles that share no sample (Copernicus-style) and the
    single file they were cut from, reprojected with ``auto``."""
    data = fractal((60, 60), seed=3)
    paths = []
    for i, (r0, r1) in enumerate([(0, 30), (30, 60)]):
        for j, (c0, c1) in enumerate([(0, 30), (30, 60)]):
            piece = np.ascontiguousarray(data[r0:r1, c0:c1])
            at = (10.0 + c0 * DEG, 45.0 - r0 * DEG)
            path = tmp_path / f"p{i}{j}.tif"
            paths.append(write_dem(path, piece, crs="EPSG:4326", origin=at, cell=DEG))
    whole = write_dem(tmp_path / "w.tif", data, crs="EPSG:4326", origin=(10.0, 45.0), cell=DEG)
    opts = TileOptions(block_size=33, dst_crs="auto")
    with pytest.MonkeyPatch.context() as mp:
        if not seams:  # (what the tiler did: each tile cut at its own sample hull)
            mp.setattr("tiler.mosaic_plan._with_seams", lambda placed, crss, target: placed)
        pair = tile(paths, tmp_path / f"pair{seams}.zarr", opts)
    one = tile(whole, tmp_path / "one.zarr", opts)
    assert pair.meta.geotransform == one.meta.geotransform
    return pair, one


def test_abutting_tiles_reprojected_lose_no_terrain_at_their_seams(tmp_path):
    """Tiles side by side without a shared row or column: the target pixels between the last
    sample of one and the first of the next lay in neither tile's sample hull and were nodata
    (a stripe through the DEM, exit 0). They now hold the tile's edge-held value (as a
    gdalwarp of the tiles): the single file's valid samples exactly, heights within 3 m (one
    step of this surface's slope across half a pixel)."""
    pair, one = _abutting(tmp_path)
    hp, vp = store_array(pair)
    ho, vo = store_array(one)
    assert (vo & ~vp).sum() == 0 and (vp & ~vo).sum() == 0  # none lost, none invented
    assert np.abs(hp - ho)[vp].max() <= 3.0


def test_a_positive_control_the_seam_stripe_is_caught(tmp_path):
    pair, one = _abutting(tmp_path, seams=False)
    lost = store_array(one)[1] & ~store_array(pair)[1]
    assert lost.sum() > 50  # (both seams, crossing the DEM)


def test_without_a_target_crs_tiles_across_the_antimeridian_are_warned_about(tmp_path, caplog):
    """Without `--dst-crs` such tiles lie losslessly on a grid in degrees that runs the long way
    round (a 2° DEM as 360° of columns, mostly empty), with no word; now a warning names
    `--dst-crs auto`. The control: two tiles side by side elsewhere plan quietly."""
    import logging

    data = fractal((61, 61), seed=3)
    west = write_dem(tmp_path / "w.tif", np.ascontiguousarray(data[:, :31]), crs="EPSG:4326",
                     origin=(179.0, -16.0), cell=DEG)  # fmt: skip
    east = write_dem(tmp_path / "e.tif", np.ascontiguousarray(data[:, 30:]), crs="EPSG:4326",
                     origin=(-180.0, -16.0), cell=DEG)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="tiler.mosaic_plan"):
        spec = plan_mosaic([str(west), str(east)])
    assert spec.width > 10_000  # (the long way round, as before: lossless, but mostly empty)
    assert "both sides of the antimeridian" in caplog.text and "--dst-crs auto" in caplog.text
    caplog.clear()
    a = write_dem(tmp_path / "a.tif", np.ascontiguousarray(data[:, :31]), crs="EPSG:4326",
                  origin=(10.0, 45.0), cell=DEG)  # fmt: skip
    b = write_dem(tmp_path / "b.tif", np.ascontiguousarray(data[:, 30:]), crs="EPSG:4326",
                  origin=(10.0 + 30 * DEG, 45.0), cell=DEG)  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="tiler.mosaic_plan"):
        plan_mosaic([str(a), str(b)])
    assert "antimeridian" not in caplog.text


def test_a_source_past_180_in_a_datum_the_wrap_would_lose_is_refused(tmp_path):
    """Wrapping a CRS at ±180° goes through a PROJ string, which keeps no datum shift: a NAD27
    source at 179..181 would be placed ~265 m off (exit 0). It is refused when planned,
    naming the file and the gdalwarp that fixes it; WGS 84 (the control) is wrapped."""
    data = fractal((61, 61), seed=3)
    nad27 = write_dem(tmp_path / "nad27.tif", data, crs="EPSG:4267", origin=(179.0, 54.0),
                      cell=DEG)  # fmt: skip
    with pytest.raises(SourceError, match=r"nad27\.tif.*datum shift.*gdalwarp -t_srs EPSG:4326"):
        plan_mosaic([str(nad27)], dst_crs="auto")
    wgs = write_dem(tmp_path / "wgs.tif", data, crs="EPSG:4326", origin=(179.0, 52.0), cell=DEG)
    assert plan_mosaic([str(wgs)], dst_crs="auto").width > 0
