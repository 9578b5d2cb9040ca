"""tiler.synth: a deterministic fractal DEM, identical however it is split, in bounded memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import rasterio
from hypothesis import given, settings
from hypothesis import strategies as st

from tiler.errors import SourceError
from tiler.synth import DTYPES, synth_array, synth_dem

FULL = slice(None)


def read(path):
    with rasterio.open(path) as ds:
        return ds.read(1), ds.profile


@pytest.fixture(scope="module")
def whole_97():
    """The whole 97 x 97 DEM of seed 5 in float64, the reference for the split tests."""
    return synth_array(FULL, FULL, 97, seed=5, dtype="float64")


# --- determinism ---------------------------------------------------------------------------------


def test_same_seed_gives_the_same_file_data_and_another_seed_does_not(tmp_path):
    synth_dem(tmp_path / "a.tif", 200, seed=7)
    synth_dem(tmp_path / "b.tif", 200, seed=7)
    synth_dem(tmp_path / "c.tif", 200, seed=8)
    a, _ = read(tmp_path / "a.tif")
    b, _ = read(tmp_path / "b.tif")
    c, _ = read(tmp_path / "c.tif")
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(np.int32) - c).mean() > 100  # a different landscape, not a jitter


def test_negative_and_huge_seeds_are_accepted_and_distinct():
    a = synth_array(FULL, FULL, 33, seed=-1)
    b = synth_array(FULL, FULL, 33, seed=2**64 - 1)
    c = synth_array(FULL, FULL, 33, seed=2**70 + 3)
    assert np.isfinite(a).all() and np.isfinite(c).all()
    np.testing.assert_array_equal(a, b)  # seeds are taken modulo 2**64
    assert not np.array_equal(a, c)


# --- split invariance ----------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_window_split_does_not_change_a_single_bit(tmp_path, dtype):
    synth_dem(tmp_path / "a.tif", 300, seed=3, dtype=dtype, window=64)
    synth_dem(tmp_path / "b.tif", 300, seed=3, dtype=dtype, window=100)
    a, _ = read(tmp_path / "a.tif")
    b, _ = read(tmp_path / "b.tif")
    assert a.dtype == np.dtype(dtype)
    assert a.tobytes() == b.tobytes()
    whole = synth_array(FULL, FULL, 300, seed=3, dtype=dtype)
    assert a.tobytes() == whole.tobytes()


@settings(max_examples=40, deadline=None)
@given(
    r=st.tuples(st.integers(0, 97), st.integers(0, 97)).map(sorted),
    c=st.tuples(st.integers(0, 97), st.integers(0, 97)).map(sorted),
)
def test_any_window_equals_the_same_area_of_the_whole_raster(whole_97, r, c):
    part = synth_array(slice(*r), slice(*c), 97, seed=5, dtype="float64")
    assert part.shape == (r[1] - r[0], c[1] - c[0])
    assert part.tobytes() == whole_97[r[0] : r[1], c[0] : c[1]].tobytes()


def test_windows_taller_than_a_strip_and_single_columns_match(whole_97):
    # A 1-column window is computed as one tall strip, a 1-row window as one short strip.
    column = synth_array(FULL, slice(40, 41), 97, seed=5, dtype="float64")
    row = synth_array(slice(96, 97), FULL, 97, seed=5, dtype="float64")
    assert column.tobytes() == whole_97[:, 40:41].tobytes()
    assert row.tobytes() == whole_97[96:97].tobytes()


def test_dtypes_are_the_float64_samples_rounded_or_cast(whole_97):
    f32 = synth_array(FULL, FULL, 97, seed=5, dtype="float32")
    i16 = synth_array(FULL, FULL, 97, seed=5, dtype="int16")
    np.testing.assert_array_equal(f32, whole_97.astype(np.float32))
    np.testing.assert_array_equal(i16, np.round(whole_97).astype(np.int16))
    assert (f32 != np.round(f32)).mean() > 0.9  # fractional metres are kept


# --- looks like terrain --------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_values_are_plausible_terrain(seed):
    z = synth_array(FULL, FULL, 257, seed=seed, dtype="float64")
    assert z.min() >= 0.0 and z.max() < 3000.0  # base 200 m + relief 2500 m, floored above 0
    assert z.std() > 300.0  # lowlands and mountains, not a flat plate
    assert np.percentile(z, 99) - np.percentile(z, 1) > 1500.0
    # Smooth at the sample scale: neighbours differ far less than the relief.
    assert np.abs(np.diff(z, axis=0)).mean() < 60.0
    assert np.abs(np.diff(z, axis=1)).mean() < 60.0
    # Rough at every scale: the finest octaves are present.
    assert np.abs(np.diff(z, 2, axis=1)).mean() > 1.0


def test_base_and_relief_are_an_affine_map():
    t = synth_array(FULL, FULL, 65, seed=9, relief=1.0, base=0.0, dtype="float64")
    z = synth_array(FULL, FULL, 65, seed=9, relief=1000.0, base=-300.0, dtype="float64")
    np.testing.assert_allclose(z, t * 1000.0 - 300.0, rtol=0, atol=1e-9)
    flat = synth_array(FULL, FULL, 65, seed=9, relief=0.0, base=42.0, dtype="float64")
    assert (flat == 42.0).all()


def test_larger_rasters_show_the_same_landscape_at_a_finer_resolution():
    coarse = synth_array(FULL, FULL, 257, seed=4, dtype="float64")
    fine = synth_array(FULL, FULL, 1025, seed=4, dtype="float64")[::4, ::4]
    assert np.corrcoef(coarse.ravel(), fine.ravel())[0, 1] > 0.99
    assert np.abs(fine - coarse).mean() < 25.0  # only the extra fine octaves differ


def test_int16_clips_instead_of_wrapping():
    z = synth_array(FULL, FULL, 65, seed=1, relief=200_000.0, base=-50_000.0, dtype="int16")
    ref = synth_array(FULL, FULL, 65, seed=1, relief=200_000.0, base=-50_000.0, dtype="float64")
    assert z.min() == -32768 and z.max() == 32767
    np.testing.assert_array_equal(z, np.clip(np.round(ref), -32768, 32767).astype(np.int16))


def test_smallest_raster():
    z = synth_array(FULL, FULL, 2, dtype="float64")
    assert z.shape == (2, 2) and np.isfinite(z).all()


# --- the GeoTIFF ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_geotiff_dtype_crs_transform_and_layout(tmp_path, dtype):
    path = tmp_path / "dem.tif"
    synth_dem(
        path, 600, seed=2, dtype=dtype, cell_size=10.0, origin=(300000.0, 4000000.0),
        crs="EPSG:32632", window=256,
    )  # fmt: skip
    data, profile = read(path)
    assert data.dtype == np.dtype(dtype) and data.shape == (600, 600)
    assert profile["count"] == 1
    assert profile["crs"].to_epsg() == 32632
    assert tuple(profile["transform"])[:6] == (10.0, 0.0, 300000.0, 0.0, -10.0, 4000000.0)
    assert profile["nodata"] is None
    assert profile["tiled"] and profile["blockxsize"] == profile["blockysize"] == 512
    assert profile["compress"] in ("zstd", "deflate")
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE").get("PREDICTOR") == ("2" if dtype == "int16" else "3")
    assert data.tobytes() == synth_array(FULL, FULL, 600, seed=2, dtype=dtype).tobytes()


def test_default_georeferencing(tmp_path):
    synth_dem(tmp_path / "dem.tif", 64)
    _, profile = read(tmp_path / "dem.tif")
    assert profile["crs"].to_epsg() == 32633
    assert tuple(profile["transform"])[:6] == (30.0, 0.0, 500000.0, 0.0, -30.0, 5000000.0)
    assert profile["dtype"] == "int16"


def test_progress_is_reported_after_each_window(tmp_path):
    calls = []
    synth_dem(tmp_path / "dem.tif", 100, window=32, progress=lambda d, t: calls.append((d, t)))
    assert len(calls) == 16  # 4 x 4 windows (32, 32, 32, 4)
    assert all(t == 100 * 100 for _, t in calls)
    done = [d for d, _ in calls]
    assert done == sorted(done) and done[0] == 32 * 32 and done[-1] == 100 * 100


def test_writing_4097_squared_does_not_hold_the_raster_in_memory(tmp_path):
    full_float64 = 4097 * 4097 * 8  # 134 MB
    tracemalloc.start()
    try:
        synth_dem(tmp_path / "big.tif", 4097, seed=1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20 < full_float64
    with rasterio.open(tmp_path / "big.tif") as ds:
        assert (ds.width, ds.height) == (4097, 4097)
        corner = ds.read(1, window=((4000, 4097), (4000, 4097)))
    expected = synth_array(slice(4000, 4097), slice(4000, 4097), 4097, seed=1, dtype="int16")
    np.testing.assert_array_equal(corner, expected)


# --- bad arguments -------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [1, 0, -5, 2.5, True, "64"])
def test_bad_size_is_a_source_error_naming_it(tmp_path, size):
    with pytest.raises(SourceError, match=repr(size).replace(".", r"\.")):
        synth_dem(tmp_path / "x.tif", size)
    assert not (tmp_path / "x.tif").exists()


def test_bad_dtype_lists_the_choices(tmp_path):
    with pytest.raises(SourceError, match=r"int16, float32.*'int8'"):
        synth_dem(tmp_path / "x.tif", 64, dtype="int8")


@pytest.mark.parametrize("window", [8, 15, 0, 16.0])
def test_bad_window_is_a_source_error_naming_it(tmp_path, window):
    with pytest.raises(SourceError, match=rf"window.*{window}"):
        synth_dem(tmp_path / "x.tif", 64, window=window)


def test_source_error_is_a_value_error(tmp_path):
    with pytest.raises(ValueError, match="1"):
        synth_dem(tmp_path / "x.tif", 1)


@pytest.mark.parametrize(
    ("rows", "cols", "message"),
    [
        (slice(0, 10, 2), FULL, "step"),
        (slice(-1, 10), FULL, "rows"),
        (FULL, slice(5, 70), "cols"),
        (slice(8, 4), FULL, "rows"),
    ],
)
def test_synth_array_rejects_bad_slices(rows, cols, message):
    with pytest.raises(SourceError, match=message):
        synth_array(rows, cols, 64)


def test_synth_array_rejects_bad_dtype_and_size():
    with pytest.raises(SourceError, match="'uint8'"):
        synth_array(FULL, FULL, 64, dtype="uint8")
    with pytest.raises(SourceError, match="1"):
        synth_array(FULL, FULL, 1)


def test_the_cli_takes_the_cell_size(tmp_path):
    """`synth` placed every DEM at 30 m cells (a 2^20+1 one 31,457 km wide, past its UTM
    zone and to infinite longitudes); `--cell-size` chooses. Control: the default is 30 m."""
    from typer.testing import CliRunner

    from cli.main import app

    r = CliRunner().invoke(
        app, ["synth", str(tmp_path / "a.tif"), "--size", "33", "--cell-size", "2.5"]
    )
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["synth", str(tmp_path / "b.tif"), "--size", "33"])
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "a.tif") as a, rasterio.open(tmp_path / "b.tif") as b:
        assert a.transform.a == 2.5 and b.transform.a == 30.0
        np.testing.assert_array_equal(a.read(1), b.read(1))  # the same samples, smaller cells
    r = CliRunner().invoke(
        app, ["synth", str(tmp_path / "c.tif"), "--size", "33", "--cell-size", "0"]
    )
    assert r.exit_code == 2 and "--cell-size" in r.output
