"""Streaming a store with a band scale and heights in feet: resident levels are metres."""

from __future__ import annotations

import numpy as np
import rasterio
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


def test_streamed_levels_are_the_stores_metres(tmp_path):
    src = write_dem(tmp_path / "ft.tif", fractal((257, 257), 5), cell=10.0)
    with rasterio.open(src, "r+") as ds:
        ds.scales, ds.units = (0.5,), ("ft",)
    store = tile(src, tmp_path / "ft.zarr", TileOptions(block_size=65))
    z0, z1 = store.meta.extra["value_range"]
    assert 0.5 * 0.3048 * 300 < z0 < z1 < 0.5 * 0.3048 * 800  # metres, not stored units
    cams = default_flythrough(store.grid, z0, z1, 10, 60.0, viewport=(160, 120))
    checked = 0
    with open_session(store, budget_mb=32, workers=1) as s:
        for cam in cams:
            f = s.update(cam, wait=True)
        for b, (have, _) in f.blocks.items():
            for got, ref in zip(s.levels(b), store.read_levels(b, have), strict=True):
                assert got.dtype == np.float64
                np.testing.assert_array_equal(got, ref)
                checked += 1
    assert checked > 0
