"""A ``--precision`` store records the height range of what it holds. ``index/zmin``/``zmax``
(and ``info``'s values) were taken from the source before rounding: a peak of 100.8 m at a
0.5 m step read back as 101.0 m above the recorded 100.8 m top, so culling boxes and the near
plane's ground clearance (``streamer.clip``) trusted a surface half a step too low. The control:
a lossless store records the source's range exactly."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import write_dem

from tiler.tile import TileOptions, tile


@pytest.mark.parametrize(("precision", "top"), [(0.5, 101.0), (None, np.float32(100.8))])
def test_the_recorded_range_covers_the_heights_read(tmp_path, precision, top):
    dem = np.full((65, 65), 100.0, np.float32)
    dem[30, 30] = 100.8
    s = tile(write_dem(tmp_path / "d.tif", dem), tmp_path / "s.zarr",
             TileOptions(block_size=65, workers=1, precision=precision))  # fmt: skip
    block = s.read_block((0, 0))
    assert float(block.max()) == float(top)
    assert float(s.index.zmax[0, 0]) == float(block.max())
    assert float(s.index.zmin[0, 0]) == float(block.min()) == 100.0
    assert s.meta.extra["value_range"] == [100.0, float(top)]
