"""The synthetic DEM writer: deterministic, window-split invariant, bounded memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import rasterio

from tiler.errors import SourceError
from tiler.synth import synth_array, synth_dem


def read(path):
    with rasterio.open(path) as ds:
        return ds.read(1), ds.profile


@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_deterministic_and_split_invariant(tmp_path, dtype):
    synth_dem(tmp_path / "a.tif", 300, seed=3, dtype=dtype, window=64)
    synth_dem(tmp_path / "b.tif", 300, seed=3, dtype=dtype, window=100)
    synth_dem(tmp_path / "c.tif", 300, seed=4, dtype=dtype, window=100)
    a, prof = read(tmp_path / "a.tif")
    b, _ = read(tmp_path / "b.tif")
    c, _ = read(tmp_path / "c.tif")
    assert a.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(
        a[50:90, 120:200], synth_array(slice(50, 90), slice(120, 200), 300, 3, dtype=dtype)
    )
    assert prof["crs"].to_epsg() == 32633 and prof["transform"].a == 30.0


def test_looks_like_terrain(tmp_path):
    synth_dem(tmp_path / "a.tif", 257, seed=1)
    a, _ = read(tmp_path / "a.tif")
    assert a.std() > 50  # not flat
    assert a.min() > -500 and a.max() < 3500  # around base 200 m + relief 2500 m
    assert np.abs(np.diff(a.astype(int), axis=1)).mean() < 100  # smooth, not noise


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"size": 1}, "size"),
        ({"size": 64, "dtype": "int8"}, "int16, float32"),
        ({"size": 64, "window": 8}, "window"),
    ],
    ids=["size", "dtype", "window"],
)
def test_bad_arguments(tmp_path, kwargs, message):
    with pytest.raises(SourceError, match=message):
        synth_dem(tmp_path / "x.tif", **kwargs)


def test_memory_is_bounded_by_the_window(tmp_path):
    tracemalloc.start()
    synth_dem(tmp_path / "big.tif", 2049, seed=2, window=256)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    full = 2049 * 2049 * 8  # the whole raster in float64 would be 33.6 MB
    assert peak < full / 4
