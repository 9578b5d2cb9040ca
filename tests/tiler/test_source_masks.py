"""A source's GDAL mask (a per-dataset mask or an alpha band) marks nodata, as GDAL's warper
already took it when reprojecting; rasters without a geotransform are refused with what they
have instead and how to grid them. Each case beside its control (the same samples unmasked, a
georeferenced raster)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from demtools import fractal, write_dem
from rasterio.control import GroundControlPoint
from rasterio.crs import CRS
from rasterio.enums import ColorInterp
from rasterio.transform import from_origin
from typer.testing import CliRunner

from cli.main import app
from tiler.errors import SourceError
from tiler.mosaic import MosaicReader, plan_mosaic
from tiler.resume import source_fingerprint
from tiler.tile import TileOptions, tile

PROFILE = dict(
    driver="GTiff", count=1, crs="EPSG:32633", transform=from_origin(500000.0, 5e6, 30.0, 30.0)
)


def _masked(path: Path, data: np.ndarray, valid: np.ndarray) -> Path:
    """A GeoTIFF with an internal per-dataset mask (GDAL's ``.msk`` kind), no nodata value."""
    h, w = data.shape
    with (
        rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True),
        rasterio.open(path, "w", width=w, height=h, dtype=data.dtype, **PROFILE) as dst,
    ):
        dst.write(data, 1)
        dst.write_mask(np.where(valid, 255, 0).astype(np.uint8))
    return path


def _gray_alpha(path: Path, data: np.ndarray, valid: np.ndarray) -> Path:
    h, w = data.shape
    prof = dict(PROFILE, count=2)
    with rasterio.open(path, "w", width=w, height=h, dtype="uint8", **prof) as dst:
        dst.write(data, 1)
        dst.write(np.where(valid, 255, 0).astype(np.uint8), 2)
        dst.colorinterp = [ColorInterp.gray, ColorInterp.alpha]
    return path


def _stored(store) -> tuple[np.ndarray, np.ndarray]:
    """The store's finest samples and mask (one block)."""
    (b,) = list(store.meta.grid.blocks())
    h, w = store.meta.height, store.meta.width
    mask = store.read_mask(b)
    return store.read_block(b, store.meta.k)[:h, :w], (
        np.ones((h, w), bool) if mask is None else mask[:h, :w]
    )


def test_a_per_dataset_mask_is_nodata(tmp_path):
    data = fractal((60, 50), 1)
    valid = np.ones(data.shape, bool)
    valid[:, :20] = False
    valid[45:, 30:] = False
    src = _masked(tmp_path / "m.tif", data, valid)
    s = tile(src, tmp_path / "m.zarr", TileOptions(block_size=65, workers=1))
    assert s.meta.nodata == -32768  # chosen: the source declares none
    h, m = _stored(s)
    assert np.array_equal(m, valid)
    assert np.array_equal(h[valid], data[valid])
    # the control: the same samples unmasked are all terrain, with no nodata value
    plain = write_dem(tmp_path / "p.tif", data)
    s = tile(plain, tmp_path / "p.zarr", TileOptions(block_size=65, workers=1))
    assert s.meta.nodata is None and _stored(s)[1].all()


def test_an_alpha_band_is_nodata_and_the_reprojection_agrees(tmp_path):
    data = (fractal((60, 50), 2) % 200 + 20).astype(np.uint8)
    valid = np.ones(data.shape, bool)
    valid[:25] = False
    src = _gray_alpha(tmp_path / "a.tif", data, valid)
    s = tile(src, tmp_path / "a.zarr", TileOptions(block_size=65, workers=1))
    assert s.meta.nodata == 0
    h, m = _stored(s)
    assert np.array_equal(m, valid) and np.array_equal(h[valid], data[valid])
    # GDAL's warper applied the mask before: reprojected, the masked rows stay nodata
    opts = TileOptions(block_size=65, workers=1, dst_crs="EPSG:32633", resampling="nearest")
    w = tile(src, tmp_path / "w.zarr", opts)
    hw, mw = _stored(w)
    assert not mw[:20].any() and mw[30:55, 2:-2].all(), (mw[:20].sum(), mw[30:55].mean())


def test_a_masked_source_is_filled_by_the_next_source(tmp_path):
    data = fractal((40, 40), 3)
    valid = np.ones(data.shape, bool)
    valid[10:20, 10:30] = False
    under = fractal((40, 40), 4)
    first = _masked(tmp_path / "first.tif", data, valid)
    second = write_dem(tmp_path / "second.tif", under)
    with MosaicReader(plan_mosaic([first, second])) as r:
        got = r.read_window(0, 0, 40, 40)
    assert np.array_equal(got, np.where(valid, data, under))  # first-valid: the mask is a hole


def test_a_valid_sample_equal_to_the_chosen_nodata_is_refused(tmp_path):
    data = (fractal((40, 30), 5) % 200 + 20).astype(np.uint8)
    valid = np.ones(data.shape, bool)
    valid[:5] = False
    data[30, 7] = 0  # valid, but 0 is what masked uint8 samples become
    src = _gray_alpha(tmp_path / "a.tif", data, valid)
    with pytest.raises(SourceError, match=r"valid samples equal to 0.*-a_nodata"):
        tile(src, tmp_path / "a.zarr", TileOptions(block_size=33, workers=1))
    data[30, 7] = 1  # the control
    tile(_gray_alpha(tmp_path / "b.tif", data, valid), tmp_path / "b.zarr", TileOptions(33))


def test_an_unmasked_source_keeps_its_fingerprint_layout(tmp_path):
    """Stores tiled before ``masked`` existed still resume and repair: an unmasked source's
    fingerprint is the one of the fields it had then (a masked one's differs, as its data)."""
    import hashlib
    from dataclasses import astuple, fields, replace
    from os.path import basename

    from rasterio.windows import Window

    from tiler.mosaic import SourceInfo

    names = [f.name for f in fields(SourceInfo)]
    # the fields of the stores tiled before ``masked``: those after it are not fingerprinted
    first = ["path", "width", "height", "transform", "crs_wkt", "dtype", "nodata", "scale"]
    first += ["offset", "units", "size_bytes", "footprint", "hull", "masked"]
    assert names[: len(first)] == first, names
    src = write_dem(tmp_path / "d.tif", fractal((300, 280), 6))
    with rasterio.open(src, "r+") as ds:  # (a label, not the data: the fingerprint is the same)
        ds.update_tags(AREA_OR_POINT="Point")
    with MosaicReader(plan_mosaic([src])) as r:
        assert r.spec.sources[0].area_or_point == "Point"
        h = hashlib.blake2b(digest_size=16)
        parts = [(basename(s.path), *astuple(s)[1 : len(first) - 1]) for s in r.spec.sources]
        h.update(repr((astuple(replace(r.spec, sources=())), parts)).encode())
        for rr, cc in ((0, 0), (150, 140), (299, 279)):
            r0, c0 = max(0, min(rr, 300 - 256)), max(0, min(cc, 280 - 256))
            win = Window(c0, r0, min(256, 280 - c0), min(256, 300 - r0))
            h.update(np.ascontiguousarray(r.read(1, window=win)).tobytes())
        assert source_fingerprint(r, 1) == h.hexdigest()
    valid = np.ones((300, 280), bool)
    valid[0, 0] = False
    m = _masked(tmp_path / "m.tif", fractal((300, 280), 6), valid)
    with MosaicReader(plan_mosaic([m])) as r2:
        assert source_fingerprint(r2, 1) != h.hexdigest()


def _no_transform(path: Path, data: np.ndarray, gcps: bool = False) -> Path:
    h, w = data.shape
    with rasterio.open(
        path, "w", driver="GTiff", width=w, height=h, count=1, dtype=data.dtype
    ) as d:
        d.write(data, 1)
        if gcps:
            pts = [(0, 0), (0, w), (h, 0), (h, w)]
            d.gcps = (
                [GroundControlPoint(r, c, 5e5 + 30 * c, 5e6 - 30 * r) for r, c in pts],
                CRS.from_epsg(32633),
            )
    return path


@pytest.mark.parametrize(
    ("gcps", "needle"),
    [
        (False, r"not georeferenced .*gdal_translate -a_ullr 0 40 30 0"),
        (True, r"4 ground control points.*gdalwarp -t_srs EPSG:32633"),
    ],
)
def test_a_raster_without_a_geotransform_is_refused_with_the_way_to_grid_it(tmp_path, gcps, needle):
    src = _no_transform(tmp_path / "n.tif", fractal((40, 30), 7), gcps)
    for dst_crs in (None, "auto"):  # (the advice was "give a target CRS", then "give none")
        with pytest.raises(SourceError, match=needle):
            tile(src, tmp_path / "n.zarr", TileOptions(block_size=33, dst_crs=dst_crs))
    r = CliRunner().invoke(app, ["tile", str(src), str(tmp_path / "c.zarr")])
    assert r.exit_code == 2 and "rotated" not in r.output, r.output
    assert "NotGeoreferencedWarning" not in r.output, r.output
    # the control: the advice's grid (north-up, one unit per sample, no CRS) tiles
    gridded = write_dem(tmp_path / "g.tif", fractal((40, 30), 7), crs=None, origin=(0, 40), cell=1)
    assert tile(gridded, tmp_path / "g.zarr", TileOptions(block_size=33)).meta.height == 40


def test_a_south_up_masked_source_flips_its_mask_with_its_samples(tmp_path):
    data = fractal((40, 30), 8)
    valid = np.ones(data.shape, bool)
    valid[:8, :5] = False  # the file's first rows: the south-west corner
    h, w = data.shape
    prof = dict(PROFILE, transform=rasterio.Affine(30.0, 0.0, 5e5, 0.0, 30.0, 5e6 - 30.0 * h))
    with (
        rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True),
        rasterio.open(tmp_path / "s.tif", "w", width=w, height=h, dtype=data.dtype, **prof) as d,
    ):
        d.write(data, 1)
        d.write_mask(np.where(valid, 255, 0).astype(np.uint8))
    s = tile(tmp_path / "s.tif", tmp_path / "s.zarr", TileOptions(block_size=65, workers=1))
    got, mask = _stored(s)
    assert np.array_equal(mask, valid[::-1]) and not mask[-8:, :5].any()
    assert np.array_equal(got[mask], data[::-1][valid[::-1]])


def test_a_damaged_source_tile_fails_naming_the_file_and_window(tmp_path):
    """A deflate tile zeroed in the middle: GDAL's read error became "RasterioIOError: Read
    failed" without the file or where; it is a SourceReadError (exit 1) naming both."""
    from tiler.errors import SourceReadError

    data = fractal((600, 520), 9)
    prof = dict(PROFILE, compress="deflate", tiled=True, blockxsize=128, blockysize=128)
    good = tmp_path / "good.tif"
    with rasterio.open(good, "w", width=520, height=600, dtype=data.dtype, **prof) as d:
        d.write(data, 1)
    with rasterio.open(good) as d:  # tile (x 3, y 1): outside the fingerprint's three windows
        off = int(d.get_tag_item("BLOCK_OFFSET_3_1", "TIFF", bidx=1))
        size = int(d.get_tag_item("BLOCK_SIZE_3_1", "TIFF", bidx=1))
    raw = bytearray(good.read_bytes())
    raw[off + 8 : off + size - 8] = bytes(size - 16)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(bytes(raw))
    with pytest.raises(SourceReadError, match=r"reading '.*bad\.tif' failed in rows .*GDAL says"):
        tile(bad, tmp_path / "bad.zarr", TileOptions(block_size=129, workers=1))
    r = CliRunner().invoke(
        app, ["tile", str(bad), str(tmp_path / "cli.zarr"), "--block-size", "129"]
    )
    assert r.exit_code == 1 and "bad.tif" in r.output and "RasterioIOError" not in r.output, (
        r.output
    )
    # the control: the intact file tiles
    assert tile(good, tmp_path / "good.zarr", TileOptions(block_size=129, workers=1)).meta.complete


def _with_nodata_vrt(path: Path, tif: Path, shape: tuple[int, int], nodata: str) -> Path:
    """A VRT of ``tif`` (int16) declaring ``nodata`` (rasterio will not write such values)."""
    h, w = shape
    path.write_text(
        f"""<VRTDataset rasterXSize="{w}" rasterYSize="{h}">
  <SRS>EPSG:32633</SRS><GeoTransform>500000, 30, 0, 5000000, 0, -30</GeoTransform>
  <VRTRasterBand dataType="Int16" band="1"><NoDataValue>{nodata}</NoDataValue>
    <SimpleSource><SourceFilename relativeToVRT="1">{tif.name}</SourceFilename>
      <SourceBand>1</SourceBand></SimpleSource></VRTRasterBand>
</VRTDataset>"""
    )
    return path


@pytest.mark.parametrize("nodata", ["-9999.5", "0.25"])
def test_an_integer_nodata_no_sample_can_take_is_refused(tmp_path, nodata):
    """int16 with nodata -9999.5: GDAL reads no sample as nodata, the cast to int16 hid the
    samples equal to -9999 ("1 with nodata"). Refused, naming the value and the fix (rasterio
    itself drops NaN and out-of-range ones); the control, -9999 declared, hides that sample."""
    data = fractal((40, 30), 10)
    data[5, 5] = -9999
    tif = write_dem(tmp_path / "d.tif", data)
    vrt = _with_nodata_vrt(tmp_path / "d.vrt", tif, data.shape, nodata)
    with pytest.raises(SourceError, match=r"declares nodata .* for its int16.*-a_nodata"):
        tile(vrt, tmp_path / "d.zarr", TileOptions(block_size=65))
    ctl = _with_nodata_vrt(tmp_path / "ok.vrt", tif, data.shape, "-9999")
    ok = tile(ctl, tmp_path / "ok.zarr", TileOptions(block_size=65))
    assert ok.meta.nodata == -9999 and not _stored(ok)[1][5, 5] and _stored(ok)[1].sum() == 1199


def test_a_colour_band_is_tiled_with_a_warning(tmp_path, caplog):
    """An RGB image's red channel or a palette's indices went in as heights silently."""
    import logging

    data = (fractal((40, 30), 11) % 200).astype(np.uint8)
    rgb = tmp_path / "rgb.tif"
    with rasterio.open(rgb, "w", width=30, height=40, dtype="uint8", photometric="RGB",
                       **dict(PROFILE, count=3)) as d:  # fmt: skip
        for i in (1, 2, 3):
            d.write(data, i)
    pal = tmp_path / "pal.tif"
    with rasterio.open(pal, "w", width=30, height=40, dtype="uint8", **PROFILE) as d:
        d.write(data, 1)
        d.write_colormap(1, {i: (i, 255 - i, 0, 255) for i in range(256)})
    for src, what in ((rgb, "the red channel of an image"), (pal, "a palette's colour indices")):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="tiler.source_header"):
            tile(src, tmp_path / f"{src.stem}.zarr", TileOptions(block_size=65))
        assert f"band 1 of '{src}' holds {what}, not heights" in caplog.text, caplog.text
    caplog.clear()  # the control: a grey band of heights
    with caplog.at_level(logging.WARNING, logger="tiler.source_header"):
        tile(write_dem(tmp_path / "g.tif", data), tmp_path / "g.zarr", TileOptions(block_size=65))
    assert "not heights" not in caplog.text


def test_a_store_given_as_the_source_is_named(tmp_path):
    """`tile dem.zarr out.zarr` (the arguments swapped, or a store for a DEM) said "band 1 does
    not exist: 'dem.zarr' has 0 band(s)" (GDAL's zarr driver opens it with no bands)."""
    src = write_dem(tmp_path / "d.tif", fractal((40, 30), 12))
    tile(src, tmp_path / "d.zarr", TileOptions(block_size=33))
    with pytest.raises(SourceError, match=r"is a zarr store, not a DEM .*terrastream export"):
        tile(tmp_path / "d.zarr", tmp_path / "out.zarr", TileOptions(block_size=33))
    assert not (tmp_path / "out.zarr").exists()  # refused before anything was written


def test_a_crs_without_a_geotransform_is_refused(tmp_path):
    """A file with a CRS but no geotransform was tiled at x 0..w, y 0..h, its rows reversed
    (GDAL's identity read as south-up), exit 0; refused now like one without a CRS. The
    control: the same file given its corners tiles."""
    data = fractal((40, 30), 7)
    path = tmp_path / "c.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=30, height=40, count=1, dtype=data.dtype,
        crs="EPSG:32633",
    ) as d:  # fmt: skip
        d.write(data, 1)
    with pytest.raises(SourceError, match="has a CRS but no geotransform.*-a_ullr"):
        tile(path, tmp_path / "c.zarr", TileOptions(block_size=33))
    assert not (tmp_path / "c.zarr").exists()
    with rasterio.open(path, "r+") as d:
        d.transform = from_origin(500000.0, 5e6, 30.0, 30.0)
    s = tile(path, tmp_path / "c.zarr", TileOptions(block_size=65))
    assert np.array_equal(s.read_block((0, 0))[:40, :30], data)


def test_a_geotransform_that_is_not_finite_is_refused_naming_it(tmp_path):
    path = write_dem(tmp_path / "n.tif", fractal((40, 30), 7))
    with rasterio.open(path, "r+") as d:
        d.transform = rasterio.Affine(float("nan"), 0.0, float("nan"), 0.0, -30.0, 5e6)
    with pytest.raises(SourceError, match=r"geotransform that is not finite \(nan"):
        tile(path, tmp_path / "n.zarr", TileOptions(block_size=33))


def test_a_band_s_own_mask_band_is_nodata(tmp_path):
    """A band with its own mask band (a VRT's ``<MaskBand>``; GDAL's flags none of all-valid,
    per-dataset, alpha or nodata) had its masked samples tiled as heights (-32000 m, exit 0,
    ``verify --source`` ok). Control: the per-dataset mask of the same samples."""
    data = fractal((60, 50), 1)
    valid = np.ones(data.shape, bool)
    valid[10:30, 5:25] = False
    data[~valid] = -32000
    base = write_dem(tmp_path / "d.tif", data)
    msk = write_dem(tmp_path / "m.tif", np.where(valid, 255, 0).astype(np.uint8))
    vrt = tmp_path / "b.vrt"
    band = (
        '<SimpleSource><SourceFilename relativeToVRT="1">{f}</SourceFilename>'
        "<SourceBand>1</SourceBand></SimpleSource>"
    )
    with rasterio.open(base) as ds:
        gt = ", ".join(repr(v) for v in ds.transform.to_gdal())
        wkt = ds.crs.to_wkt()
    vrt.write_text(
        f'<VRTDataset rasterXSize="50" rasterYSize="60"><SRS>{wkt}</SRS>'
        f"<GeoTransform>{gt}</GeoTransform>"
        f'<VRTRasterBand dataType="{data.dtype.name.capitalize()}" band="1">'
        + band.format(f=base.name)
        + '<MaskBand><VRTRasterBand dataType="Byte">'
        + band.format(f=msk.name)
        + "</VRTRasterBand></MaskBand></VRTRasterBand></VRTDataset>"
    )
    with rasterio.open(vrt) as ds:
        assert ds.mask_flag_enums[0] == []  # the band's own mask
    s = tile(str(vrt), tmp_path / "b.zarr", TileOptions(block_size=65, workers=1))
    h, m = _stored(s)
    assert np.array_equal(m, valid) and np.array_equal(h[valid], data[valid])
    c = tile(_masked(tmp_path / "p.tif", data, valid), tmp_path / "p.zarr", TileOptions(65))
    assert np.array_equal(_stored(c)[1], m)


def _two_variable_netcdf(path: Path, z: np.ndarray) -> Path:
    """A netCDF-3 file holding ``slope`` then ``elevation`` on a 30 m UTM grid (GDAL lists
    them as subdatasets), written byte by byte (the netCDF classic format)."""
    import struct

    h, w = z.shape

    def name(s: str) -> bytes:
        b = s.encode()
        return struct.pack(">i", len(b)) + b + b"\0" * (-len(b) % 4)

    def text(k: str, v: str) -> bytes:
        b = v.encode()
        return name(k) + struct.pack(">ii", 2, len(b)) + b + b"\0" * (-len(b) % 4)

    xs = 500000 + 30 * (np.arange(w) + 0.5)
    ys = 4000000 - 30 * (np.arange(h) + 0.5)
    std = "standard_name"
    variables = [
        ("y", [0], 6, ys.astype(">f8"), [("units", "m"), (std, "projection_y_coordinate")]),
        ("x", [1], 6, xs.astype(">f8"), [("units", "m"), (std, "projection_x_coordinate")]),
        ("slope", [0, 1], 5, np.full((h, w), 7, ">f4"), [("units", "degree")]),
        ("elevation", [0, 1], 5, z.astype(">f4"), [("units", "m")]),
    ]  # fmt: skip

    def header(begins: list[int]) -> bytes:
        out = b"CDF\x01" + struct.pack(">i", 0) + struct.pack(">ii", 10, 2)
        out += name("y") + struct.pack(">i", h) + name("x") + struct.pack(">i", w)
        out += struct.pack(">ii", 0, 0) + struct.pack(">ii", 11, len(variables))
        for (n, dims, t, data, atts), begin in zip(variables, begins, strict=True):
            out += name(n) + struct.pack(">i", len(dims))
            out += b"".join(struct.pack(">i", d) for d in dims)
            out += struct.pack(">ii", 12, len(atts)) + b"".join(text(k, v) for k, v in atts)
            out += struct.pack(">iii", t, data.nbytes + (-data.nbytes % 4), begin)
        return out

    begins, offset = [], len(header([0] * len(variables)))
    for v in variables:
        begins.append(offset)
        offset += v[3].nbytes + (-v[3].nbytes % 4)
    with open(path, "wb") as f:
        f.write(header(begins))
        for v in variables:
            f.write(v[3].tobytes() + b"\0" * (-v[3].nbytes % 4))
    return path


def test_a_netcdf_of_several_variables_names_them_and_one_tiles_by_its_gdal_name(tmp_path):
    """A netCDF holding several variables was refused as "no raster bands", and the GDAL name
    of one (``NETCDF:"f.nc":elevation``) as "does not exist" (`tile`, and `verify --source`,
    which also mangled URLs); the variable now tiles and verifies, and the file's error lists
    the names to give."""
    z = fractal((40, 30), 7).astype(np.float32)
    nc = _two_variable_netcdf(tmp_path / "multi.nc", z)
    with pytest.raises(SourceError, match=r"holds 2 rasters, not one; .*netcdf:[^,]+:elevation"):
        tile(str(nc), tmp_path / "m.zarr", TileOptions(block_size=65))
    sub = f'NETCDF:"{nc}":elevation'
    s = tile(sub, tmp_path / "e.zarr", TileOptions(block_size=65))
    assert np.array_equal(s.read_block((0, 0))[:40, :30], z)
    r = CliRunner().invoke(app, ["verify", str(tmp_path / "e.zarr"), "--source", sub])
    assert r.exit_code == 0 and "source digests compared" in r.output, r.output
    listed = f"netcdf:{nc}:elevation"  # (as the message lists it: rasterio's spelling)
    assert np.array_equal(
        tile(listed, tmp_path / "l.zarr", TileOptions(65)).read_block((0, 0))[:40, :30], z
    )
    # the control: a missing plain file is still refused at once, naming it
    r = CliRunner().invoke(app, ["verify", str(tmp_path / "e.zarr"), "--source", "nope.nc"])
    assert r.exit_code == 2 and "'nope.nc' does not exist" in r.output, r.output


def test_a_multi_band_source_says_which_band_is_tiled(tmp_path, caplog):
    data = fractal((40, 30), 7)
    path = tmp_path / "two.tif"
    with rasterio.open(
        path, "w", width=30, height=40, dtype=data.dtype, **dict(PROFILE, count=2)
    ) as d:
        d.write(np.stack([data, data + 5]))
    with caplog.at_level("WARNING"):
        s = tile(path, tmp_path / "t.zarr", TileOptions(block_size=65, band=2))
    assert "has 2 bands; band 2 is read as the heights" in caplog.text
    assert np.array_equal(s.read_block((0, 0))[:40, :30], data + 5)
    caplog.clear()
    with caplog.at_level("WARNING"):
        tile(write_dem(tmp_path / "one.tif", data), tmp_path / "o.zarr", TileOptions(65))
    assert "bands" not in caplog.text  # the control: one band, nothing to say
