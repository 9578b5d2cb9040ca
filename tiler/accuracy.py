"""How far a reprojected store is from its source, measured at the source's own samples.

Each source sample's centre is mapped into the store's CRS and the store's surface is
interpolated bilinearly there; the difference to the source sample is the resampling error
(interpolation + the store's height rounding). Meant for tests and benchmarks: it holds the
store's finest level in memory, so use ``stride`` on large DEMs.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.warp import transform as warp_transform

from tiler.grid import as_index
from tiler.store import TerrainStore


def store_array(store: TerrainStore, level: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(heights, valid)`` of the whole DEM at ``level`` (default finest), block by block."""
    level = store.k if level is None else as_index(level, "level")
    step = 1 << (store.k - level)
    m = store.meta
    h, w = (m.height - 1) // step + 1, (m.width - 1) // step + 1
    out = np.zeros((h, w), dtype=np.float64)
    valid = np.zeros((h, w), dtype=bool)
    grid = store.grid
    bstep = grid.step // step
    for br, bc in grid.blocks():
        if not store.index.exists[br, bc]:
            continue
        r0, c0 = br * bstep, bc * bstep
        nr, nc = min(bstep + 1, h - r0), min(bstep + 1, w - c0)
        g = store.read_block((br, bc), level, extent=(nr, nc))
        v = store.read_mask((br, bc))[::step, ::step][:nr, :nc]
        sub = (slice(r0, r0 + nr), slice(c0, c0 + nc))
        out[sub] = np.where(v, g, out[sub])
        valid[sub] |= v
    return out, valid


def resampling_error(
    store: TerrainStore, src: str | os.PathLike, band: int = 1, stride: int = 1
) -> dict[str, Any]:
    """Max, RMS, 99th percentile and mean of |store - source| over source samples (metres).

    Samples that are nodata in the source, or fall outside the store's valid surface, are
    counted in ``skipped`` and left out.
    """
    heights, valid = store_array(store)
    grid = store.grid
    with rasterio.open(src) as ds:
        data = ds.read(band)[::stride, ::stride].astype(np.float64)
        nodata = ds.nodatavals[band - 1]
        rows, cols = np.mgrid[0 : ds.height : stride, 0 : ds.width : stride]
        xs, ys = rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel())
        src_crs = ds.crs
    ok = np.isfinite(data).ravel()
    if nodata is not None and not np.isnan(nodata):
        ok &= data.ravel() != nodata
    tx, ty = warp_transform(src_crs, CRS.from_wkt(store.meta.crs_wkt), xs, ys)
    r, c = grid.world_to_sample(np.asarray(tx), np.asarray(ty))
    r0 = np.floor(r).astype(np.int64)
    c0 = np.floor(c).astype(np.int64)
    inside = (r0 >= 0) & (c0 >= 0) & (r0 + 1 < heights.shape[0]) & (c0 + 1 < heights.shape[1])
    ok &= inside
    r0c, c0c = np.clip(r0, 0, heights.shape[0] - 2), np.clip(c0, 0, heights.shape[1] - 2)
    corners = [(0, 0), (0, 1), (1, 0), (1, 1)]
    ok &= np.all([valid[r0c + i, c0c + j] for i, j in corners], axis=0)
    fr, fc = r - r0, c - c0
    z = (
        heights[r0c, c0c] * (1 - fr) * (1 - fc)
        + heights[r0c, c0c + 1] * (1 - fr) * fc
        + heights[r0c + 1, c0c] * fr * (1 - fc)
        + heights[r0c + 1, c0c + 1] * fr * fc
    )
    err = np.abs(z[ok] - data.ravel()[ok])
    if err.size == 0:
        raise ValueError(f"no source sample of {str(src)!r} falls on the store's valid surface")
    return {
        "n": int(err.size),
        "skipped": int((~ok).sum()),
        "max": float(err.max()),
        "rms": float(np.sqrt(np.mean(err**2))),
        "p99": float(np.percentile(err, 99)),
        "mean": float(err.mean()),
    }
