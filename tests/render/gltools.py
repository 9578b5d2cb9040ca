"""Helpers for the renderer's tests: a shared headless context, tiny stores, GL error checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def make_context():
    """The shared headless EGL context (``shared_gl.gl_context``): without one the module is
    skipped with the reason, or fails with ``CI=true``."""
    from shared_gl import gl_context

    return gl_context()


def rough(n: int, seed: int, amp: float = 8.0) -> np.ndarray:
    """A rough int16 DEM of ``n x n`` samples around 800 m."""
    from demtools import fractal

    d = fractal((n, n), seed=seed).astype(np.float64)
    return np.rint((d - d.mean()) * amp + 800).astype(np.int16)


def tile_dem(tmp: Path, data: np.ndarray, block: int, **kw) -> Path:
    """Write ``data`` as a GeoTIFF and tile it; return the store path."""
    from demtools import write_dem

    from tiler.tile import TileOptions, tile

    src = write_dem(tmp / "dem.tif", data, **kw)
    dst = tmp / "s.zarr"
    tile(src, dst, TileOptions(block_size=block, workers=1))
    return dst
