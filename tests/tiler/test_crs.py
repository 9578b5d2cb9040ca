"""Geographic DEMs: choosing a metric CRS, reprojecting while tiling, refusing degree stores."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from demtools import shared_file, write_dem
from rasterio.crs import CRS
from rasterio.transform import Affine

from tiler.accuracy import resampling_error
from tiler.crs import (
    auto_crs,
    crs_name,
    parse_dst_crs,
    parse_resampling,
    require_projected,
    utm_epsg,
)
from tiler.errors import GeographicStoreError, SourceError, StoreError
from tiler.mosaic import MosaicReader, plan_mosaic
from tiler.tile import TileOptions, tile


@pytest.mark.parametrize(
    ("lon", "lat", "epsg"),
    [
        (-71.5, 44.5, 32619),  # N44W072 (White Mountains): zone 19, not 18
        (11.5, 49.5, 32632),  # N49E011: zone 32
        (-70.6, -33.4, 32719),  # Santiago: south
        (-180.0, 10.0, 32601),
        (179.99, 10.0, 32660),
        (0.0, 0.0, 32631),
    ],
    ids=["N44W072", "N49E011", "south", "west-edge", "east-edge", "origin"],
)
def test_utm_zone_of_a_point(lon, lat, epsg):
    assert utm_epsg(lon, lat) == epsg


@pytest.mark.parametrize(
    ("bounds", "expect"),
    [
        ((-72.0, 44.0, -71.0, 45.0), "EPSG:32619"),
        ((11.0, 49.0, 12.0, 50.0), "EPSG:32632"),
        ((-73.0, 44.0, -71.0, 45.0), "EPSG:32619"),  # 1 degree into zone 18: still fits
        ((-10.0, 35.0, 30.0, 60.0), "aeqd"),  # Europe: no single zone
        ((10.0, 84.5, 20.0, 86.0), "aeqd"),  # beyond UTM's latitudes
    ],
    ids=["N44W072", "N49E011", "margin", "continent", "polar"],
)
def test_auto_crs_utm_when_the_extent_fits_a_zone(bounds, expect):
    crs = auto_crs(bounds)
    if expect.startswith("EPSG"):
        assert crs == CRS.from_string(expect)
    else:
        proj = crs.to_proj4()
        assert "+proj=aeqd" in proj
        lon_c = (bounds[0] + bounds[2]) / 2
        assert f"+lon_0={lon_c:g}" in proj.replace(".000000", "")


def test_parse_dst_crs_and_resampling():
    assert parse_dst_crs("auto") == "auto" and parse_dst_crs(" AUTO ") == "auto"
    assert CRS.from_wkt(parse_dst_crs("EPSG:32619")).to_epsg() == 32619
    with pytest.raises(SourceError, match="'EPSG:999999' is not understood"):
        parse_dst_crs("EPSG:999999")
    with pytest.raises(SourceError, match="is geographic"):
        parse_dst_crs("EPSG:4326")
    assert parse_resampling("Cubic") == "cubic"
    with pytest.raises(SourceError, match="'sinc' is not one of"):
        parse_resampling("sinc")
    with pytest.raises(SourceError, match="applies when reprojecting"):
        TileOptions(resolution=30.0)
    with pytest.raises(SourceError, match="not understood"):
        TileOptions(dst_crs="nonsense")


def test_an_unknown_crs_is_one_message_not_gdal_noise_on_stderr():
    """GDAL printed "ERROR 1: PROJ: ... crs not found" to the process's stderr before the
    message. In fresh interpreters (another test may leave GDAL a handler): the control,
    outside rasterio.Env, shows the capture sees such a line."""
    import subprocess
    import sys
    from pathlib import Path

    def stderr_of(code: str) -> str:
        run = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
            cwd=Path(__file__).resolve().parents[2],
        )
        return run.stderr

    control = stderr_of(
        "from rasterio.crs import CRS\n"
        "try:\n    CRS.from_user_input('EPSG:999998')\nexcept Exception:\n    pass"
    )
    assert "ERROR 1: PROJ" in control, control
    ours = stderr_of(
        "from tiler.crs import parse_dst_crs\n"
        "try:\n    parse_dst_crs('EPSG:999998')\nexcept ValueError as e:\n    print(e)"
    )
    assert "ERROR" not in ours, ours


LON0, LAT0, CELL_DEG = -71.9, 44.9, 1.0 / 120.0


def smooth_geographic(tmp_path, name="geo.tif", shift_px=0, n=121):
    """A smooth float surface on a 30-arcsecond geographic grid (analytic, so resampling
    error is interpolation error only)."""
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64)
    lon = LON0 + (cols + 0.5) * CELL_DEG
    lat = LAT0 - (rows + 0.5) * CELL_DEG
    z = 500 + 200 * np.sin(2 * np.pi * lon / 0.5) * np.cos(2 * np.pi * lat / 0.4)
    return write_dem(
        tmp_path / name,
        z.astype(np.float32),
        crs="EPSG:4326",
        origin=(LON0 + shift_px * CELL_DEG, LAT0),
        cell=CELL_DEG,
    )


def test_geographic_store_tiles_losslessly_but_is_refused(tmp_path):
    src = smooth_geographic(tmp_path)
    store = tile(src, tmp_path / "deg.zarr", TileOptions(block_size=33))
    with rasterio.open(src) as ds:
        np.testing.assert_array_equal(store.read_block((0, 0))[:33, :33], ds.read(1)[:33, :33])
    with pytest.raises(GeographicStoreError) as e:
        require_projected(store)
    msg = str(e.value)
    assert isinstance(e.value, StoreError) and isinstance(e.value, ValueError)
    assert "EPSG:4326" in msg and "deg.zarr" in msg
    assert f"tile({str(src)!r}, dst, TileOptions(dst_crs='auto'))" in msg
    with pytest.raises(GeographicStoreError):
        require_projected(store.meta)  # the metadata alone is enough


def test_projected_store_is_accepted(tmp_path):
    src = write_dem(tmp_path / "utm.tif", np.zeros((20, 20), np.int16) + 7)
    require_projected(tile(src, tmp_path / "utm.zarr", TileOptions(block_size=17)))


def test_auto_reprojection_picks_utm_and_is_accurate(tmp_path):
    src = smooth_geographic(tmp_path)
    store = tile(src, tmp_path / "utm.zarr", TileOptions(block_size=65, dst_crs="auto"))
    assert crs_name(store.meta.crs_wkt) == "EPSG:32619"
    assert CRS.from_wkt(store.meta.extra["source_crs_wkt"]).to_epsg() == 4326
    rep = store.meta.extra["reprojection"]
    assert rep["requested"] == "auto" and rep["resampling"] == "bilinear"
    dx, dy = rep["resolution"]
    assert dx == dy and 600 < dx < 700  # the finer side of a 30" pixel at 44.4 N (~660 m)
    require_projected(store)  # now streamable
    err = resampling_error(store, src)
    assert err["n"] > 0.95 * 121 * 121
    # bilinear there and back on a 60-pixel wavelength: interpolation error only
    assert err["max"] < 2.0 and err["rms"] < 0.6, err  # measured: 1.39 and 0.51
    # positive control: the same surface one pixel off is measured as far off
    shifted = smooth_geographic(tmp_path, "shifted.tif", shift_px=1)
    assert resampling_error(store, shifted)["max"] > 10 * err["max"]


def test_explicit_crs_resolution_and_resampling(tmp_path):
    src = smooth_geographic(tmp_path, n=61)
    opts = TileOptions(block_size=33, dst_crs="EPSG:32618", resolution=1000.0, resampling="cubic")
    store = tile(src, tmp_path / "z18.zarr", opts)
    assert crs_name(store.meta.crs_wkt) == "EPSG:32618"
    a, _, c, _, e, f = store.meta.geotransform
    assert (a, e) == (1000.0, -1000.0) and c % 1000 == 0 and f % 1000 == 0  # snapped grid
    assert store.meta.extra["reprojection"]["resampling"] == "cubic"


@pytest.mark.shared_data
def test_srtm_auto_is_zone_19_and_close_to_the_source(tmp_path):
    src = shared_file("N44W072.hgt")
    store = tile(src, tmp_path / "n44.zarr", TileOptions(block_size=257, dst_crs="auto"))
    assert crs_name(store.meta.crs_wkt) == "EPSG:32619"
    err = resampling_error(store, src, stride=3)
    # measured (see notes): rms 1.47 m, p99 5.2 m, max 31 m on this rough 3" tile
    assert err["rms"] < 2.5 and err["p99"] < 8.0, err


def _south_up(path, data, x0, y0, b=0.0):
    from rasterio.transform import Affine

    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[1],
        height=data.shape[0],
        count=1,
        dtype=data.dtype,
        crs="EPSG:32633",
        transform=Affine(30.0, b, x0, 0.0, 30.0, y0),
    ) as dst:
        dst.write(data, 1)
    return path


def test_south_up_source_is_flipped_sample_for_sample(tmp_path):
    data = np.arange(20 * 30, dtype=np.int16).reshape(20, 30)
    x0, y0 = 499980.0, 4999980.0  # on the 30 m grid the target snaps to
    path = _south_up(tmp_path / "south_up.tif", data, x0, y0)
    a = tile(path, tmp_path / "a.zarr", TileOptions(block_size=33))  # (was refused)
    assert a.meta.geotransform == (30.0, 0.0, x0, 0.0, -30.0, y0 + 600.0)
    np.testing.assert_array_equal(a.read_block((0, 0))[:20, :30], data[::-1])
    # the same as GDAL's warp onto that grid (nearest: no resampling either)
    opts = TileOptions(block_size=33, dst_crs="EPSG:32633", resampling="nearest", resolution=30.0)
    s = tile(path, tmp_path / "b.zarr", opts)
    assert (s.meta.height, s.meta.width) == (20, 30)
    assert s.meta.geotransform == a.meta.geotransform
    np.testing.assert_array_equal(s.read_block((0, 0))[:20, :30], data[::-1])
    # a mosaic of it and a north-up neighbour to its east, windows across both
    east = np.arange(20 * 10, dtype=np.int16).reshape(20, 10) + 1000
    n = write_dem(tmp_path / "east.tif", east, crs="EPSG:32633", origin=(x0 + 900.0, y0 + 600.0))
    m = tile([path, n], tmp_path / "m.zarr", TileOptions(block_size=17))
    with MosaicReader(plan_mosaic([path, n])) as r:
        np.testing.assert_array_equal(
            r.read_window(3, 25, 12, 10), np.hstack([data[::-1], east])[3:15, 25:35]
        )
    assert (m.meta.height, m.meta.width) == (20, 40)
    # the control: a rotated geotransform is still refused (no flip makes it north-up)
    rot = _south_up(tmp_path / "rot.tif", data, x0, y0, b=0.5)
    with pytest.raises(SourceError, match="rotated"):
        tile(rot, tmp_path / "r.zarr", TileOptions(block_size=33))
    assert s.read_mask((0, 0))[:20, :30].all()  # edge samples on the hull are kept


# --- how far auto's azimuthal projection stretches a DEM ---------------------------------------


def test_aeqd_stretch_on_the_sphere():
    from tiler.crs import EARTH_RADIUS_M, aeqd_stretch

    reach, k = aeqd_stretch((-1.0, -1.0, 1.0, 1.0), 0.0, 0.0)
    assert reach == pytest.approx(np.radians(np.hypot(1, 1)) * EARTH_RADIUS_M, rel=1e-3)
    c = np.radians(np.hypot(1, 1))
    assert k == pytest.approx(1 + c**2 / 6, rel=1e-6)  # c / sin c for small c
    # a quarter of the globe away (a corner at 90° of arc): c / sin c = π/2
    reach, k = aeqd_stretch((-90.0, -10.0, 90.0, 10.0), 0.0, 0.0)
    assert k == pytest.approx(np.pi / 2, rel=1e-3)
    # the antipode inside the box: without bound, also across the antimeridian
    assert aeqd_stretch((-180.0, -90.0, 180.0, 90.0), 0.0, 0.0)[1] == np.inf
    assert aeqd_stretch((170.0, -5.0, 190.0, 5.0), 0.0, 0.0)[1] == np.inf
    assert aeqd_stretch((170.0, 5.0, 190.0, 15.0), 0.0, 0.0)[1] < np.inf  # antipode south of it


@pytest.mark.parametrize(
    ("bounds", "stretch"),
    [
        ((-180.5, -90.5, 180.5, 90.5), "without bound"),  # a global grid, edges past the poles
        ((-180.0, -90.0, 180.0, 90.0), "without bound"),
        ((-100.0, -40.0, 100.0, 60.0), "by 87.2 %"),  # a hemisphere
    ],
    ids=["global-grid", "global", "hemisphere"],
)
def test_auto_refuses_an_extent_no_flat_projection_holds(bounds, stretch):
    with pytest.raises(SourceError, match="a flat terrain store holds a region") as e:
        auto_crs(bounds)
    msg = str(e.value)
    assert f"stretches distances {stretch}" in msg or f"across the radius {stretch}" in msg
    assert msg.startswith("dst_crs='auto': the DEM reaches")
    assert "name a projection with dst_crs (this one, accepting the stretch: '+proj=aeqd" in msg


def test_auto_warns_of_a_stretch_past_one_percent_and_says_nothing_below(caplog):
    caplog.set_level("WARNING", logger="tiler.crs")
    auto_crs((-10.0, 35.0, 30.0, 60.0))  # Europe: 2,000 km from its centre
    assert "across the radius by 1.9 %; tile smaller parts for less" in caplog.text
    caplog.clear()
    auto_crs((10.0, 84.5, 20.0, 86.0))  # polar but small: no warning (the control)
    auto_crs((-72.0, 44.0, -71.0, 45.0))  # UTM
    assert not caplog.records


def test_a_grid_whose_first_row_is_centred_on_the_pole_tiles_with_auto(tmp_path):
    """Its pixel edges lie half a pixel past 90°N: PROJ refused the hull ("aeqd: Invalid
    latitude", exit 1); the pole's row is now kept, its samples in the store."""
    from rasterio.transform import from_origin

    data = np.full((41, 181), 300, np.int16)
    data[0] = 777  # the row on the pole
    src = write_dem(tmp_path / "cap.tif", data, crs="EPSG:4326", origin=(-181.0, 90.125),
                    cell=2.0)  # fmt: skip
    with rasterio.open(src, "r+") as f:  # 2° of longitude by 0.25° of latitude
        f.transform = from_origin(-181.0, 90.125, 2.0, 0.25)
    store = tile(src, tmp_path / "cap.zarr", TileOptions(dst_crs="auto", resampling="nearest"))
    assert store.meta.extra["value_range"] == [300, 777]


def test_a_resolution_in_the_wrong_units_is_refused_before_anything_is_written(tmp_path):
    """0.0003 (degrees, meant for a geographic source) as metres planned a 3.7e8-sample-wide
    grid and ended in a MemoryError ("Unable to allocate 125 GiB") after creating the store."""
    src = write_dem(tmp_path / "g.tif", np.full((41, 41), 100, np.int16), crs="EPSG:4326",
                    origin=(10.0, 45.0), cell=0.01)  # fmt: skip
    dst = tmp_path / "s.zarr"
    with pytest.raises(SourceError, match=r"resolution 0.0003 is [\d,]+x finer than the source's"):
        tile(src, dst, TileOptions(dst_crs="auto", resolution=0.0003))
    with pytest.raises(SourceError, match=r"resolution 5e\+06 leaves a 1x1 grid .* give at most"):
        tile(src, dst, TileOptions(dst_crs="auto", resolution=5e6))
    assert not dst.exists()
    # the controls: 8x finer than the source's pixel (786 m across at 45°N), and a coarse one
    assert tile(src, dst, TileOptions(dst_crs="auto", resolution=100.0)).grid.width > 300
    coarse = tile(src, tmp_path / "c.zarr", TileOptions(dst_crs="auto", resolution=1500.0))
    assert coarse.grid.width >= 2


LOCAL_CS = 'LOCAL_CS["unnamed",UNIT["unknown",1],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'


@pytest.mark.parametrize("dst_crs", ["auto", "EPSG:32633"])
def test_a_local_engineering_crs_is_refused_for_reprojection_with_one_message(tmp_path, dst_crs):
    """whitebox_DEM.tif's kind of CRS (x/y on no datum): `--dst-crs auto` printed PROJ's
    JSON dump and failed with exit 1; now a SourceError (exit 2) before anything is written.
    Control: the same file tiles without a target CRS."""
    import subprocess
    import sys
    from pathlib import Path

    src = write_dem(tmp_path / "local.tif", np.arange(33 * 33, dtype=np.float32).reshape(33, 33),
                    crs=LOCAL_CS)  # fmt: skip
    with rasterio.open(src) as ds:
        assert ds.crs is not None and not ds.crs.is_projected and not ds.crs.is_geographic
    with pytest.raises(SourceError, match="local engineering one .*tile it without dst_crs"):
        tile(src, tmp_path / "a.zarr", TileOptions(dst_crs=dst_crs, block_size=33))
    assert not (tmp_path / "a.zarr").exists()
    exe = Path(sys.executable).with_name("terrastream")
    run = subprocess.run(
        [str(exe), "tile", str(src), str(tmp_path / "b.zarr"), "--dst-crs", dst_crs],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2, run.stderr
    assert "tile it without --dst-crs" in run.stderr and "ERROR" not in run.stderr, run.stderr
    assert not (tmp_path / "b.zarr").exists()
    tile(src, tmp_path / "c.zarr", TileOptions(block_size=33))  # control: no target CRS
    assert (tmp_path / "c.zarr" / "zarr.json").exists()


MARS_EQC, MARS_LONLAT = "IAU_2015:49912", "IAU_2015:49900"


@pytest.mark.parametrize(
    ("src", "dst", "to"),
    [
        (MARS_EQC, "auto", "longitude/latitude, which 'auto' needs"),
        (MARS_LONLAT, "auto", "longitude/latitude, which 'auto' needs"),  # (was: an Earth UTM)
        (MARS_EQC, "EPSG:32633", "EPSG:32633"),
    ],
)
def test_a_crs_with_no_way_to_the_target_is_one_message(src, dst, to):
    """A DEM of another body: `auto` (or an Earth target) has no operation from it. A
    SourceError naming both, not GDAL's error later in the warp (or, for a Mars lon/lat
    source, an Earth UTM zone chosen from its degrees). Control: a Mars target is reachable."""
    from tiler.crs import choose_crs

    crs = CRS.from_user_input(src)
    box = (-1.0, -1.0, 1.0, 1.0) if crs.is_geographic else (0.0, 0.0, 1e5, 1e5)
    target = dst if dst == "auto" else parse_dst_crs(dst)
    with pytest.raises(SourceError, match=f"has no transformation to {to} .*name a target"):
        choose_crs(target, crs, box)
    mars = CRS.from_user_input(MARS_EQC)
    assert choose_crs(mars.to_wkt(), crs, box).to_wkt() == mars.to_wkt()  # control


def test_no_transformation_is_said_once_not_by_gdal_on_stderr():
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "from rasterio.crs import CRS\nfrom tiler.crs import choose_crs\n"
        f"try:\n    choose_crs('auto', CRS.from_user_input('{MARS_EQC}'), (0, 0, 1, 1))\n"
        "except ValueError as e:\n    print(e)"
    )
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, cwd=root)  # fmt: skip
    assert "has no transformation" in run.stdout and "ERROR" not in run.stderr, run.stderr


def test_a_source_whose_columns_run_east_to_west_is_mirrored_sample_for_sample(tmp_path):
    """A negative x pixel size (column 0 at the eastern edge) was tiled as it lay in the file:
    `export` was right but the store's grid, `info`'s extent, xarray's x and every render were
    mirrored east-west (exit 0). Now it is read mirrored, as a south-up source is flipped; the
    control: the same DEM written west-to-east gives the same store."""
    data = np.arange(20 * 30, dtype=np.int16).reshape(20, 30)
    x0, y0 = 499980.0, 5000580.0  # the west and north edges
    path = tmp_path / "west.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=30, height=20, count=1, dtype="int16",
        crs="EPSG:32633", transform=Affine(-30.0, 0.0, x0 + 900.0, 0.0, -30.0, y0),
    ) as dst:  # fmt: skip
        dst.write(data[:, ::-1], 1)  # column 0: the eastern edge
    s = tile(path, tmp_path / "w.zarr", TileOptions(block_size=33))
    assert s.meta.geotransform == (30.0, 0.0, x0, 0.0, -30.0, y0)
    np.testing.assert_array_equal(s.read_block((0, 0))[:20, :30], data)
    plain = write_dem(tmp_path / "p.tif", data, crs="EPSG:32633", origin=(x0, y0))
    p = tile(plain, tmp_path / "p.zarr", TileOptions(block_size=33))
    assert p.meta.geotransform == s.meta.geotransform
    np.testing.assert_array_equal(p.read_block((0, 0)), s.read_block((0, 0)))
    # both ways at once (south-up and east-to-west): rows and columns turned
    both = tmp_path / "both.tif"
    with rasterio.open(
        both, "w", driver="GTiff", width=30, height=20, count=1, dtype="int16",
        crs="EPSG:32633", transform=Affine(-30.0, 0.0, x0 + 900.0, 0.0, 30.0, y0 - 600.0),
    ) as dst:  # fmt: skip
        dst.write(data[::-1, ::-1], 1)
    b = tile(both, tmp_path / "b.zarr", TileOptions(block_size=33))
    assert b.meta.geotransform == s.meta.geotransform
    np.testing.assert_array_equal(b.read_block((0, 0))[:20, :30], data)


def test_a_local_crs_in_feet_is_not_taken_as_metres():
    """An engineering (LOCAL_CS) CRS in feet had no unit as far as the renderer knew (rasterio
    defines no linear-units factor but for projected CRSs), so it was drawn as metres;
    control: the same CRS in metres."""
    from tiler.crs import non_metre_unit

    ft = 'LOCAL_CS["site ft",UNIT["foot",0.3048],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
    assert non_metre_unit(ft) == ("foot", 0.3048)
    assert non_metre_unit(ft.replace('"foot",0.3048', '"metre",1')) is None
