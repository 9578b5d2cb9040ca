"""Rebuild a GeoTIFF of the whole DEM from a store at any level, block row by block row."""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.windows import Window

from tiler.encoding import decode_grid, dequantise
from tiler.errors import StoreError
from tiler.store import TerrainStore


def export_shape(store: TerrainStore, level: int) -> tuple[int, int, int]:
    """``(height, width, step)`` of the raster at ``level`` (every ``step``-th source sample)."""
    step = 1 << (store.k - level)
    m = store.meta
    return (m.height - 1) // step + 1, (m.width - 1) // step + 1, step


def export_geotiff(
    store: TerrainStore,
    out: str | os.PathLike,
    level: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Write the DEM at ``level`` (default finest) to a tiled GeoTIFF; nodata restored.

    At the finest level of a lossless store the samples are bit-identical to the source's, with
    the same CRS and transform. Coarser levels keep every ``2**(k-level)``-th sample, so the
    transform's pixel size grows by that factor (its origin stays on sample (0, 0)).
    """
    k = store.k
    level = k if level is None else int(level)
    if not 0 <= level <= k:
        raise StoreError(f"--level must be in 0..{k} for this store, got {level}")
    m = store.meta
    height, width, step = export_shape(store, level)
    a, b, c, d, e, f = m.geotransform
    transform = Affine(a * step, b, c, d, e * step, f)
    if step > 1:  # keep sample centres: the first sample's centre stays where it was
        transform = Affine(
            a * step, b, c + a * 0.5 - a * step * 0.5, d, e * step, f + e * 0.5 - e * step * 0.5
        )
    dtype = np.dtype(m.dtype)
    nodata = m.nodata
    if nodata is None and dtype.kind == "f" and bool(store.index.has_nodata.any()):
        nodata = float("nan")
    profile = {
        "driver": "GTiff",
        "width": width,
        "height": height,
        "count": 1,
        "dtype": dtype.name,
        "crs": m.crs_wkt,
        "transform": transform,
        "nodata": nodata,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
        "predictor": 3 if dtype.kind == "f" else 2,
        "BIGTIFF": "IF_SAFER",
    }
    if width < 256 or height < 256:
        profile.pop("blockxsize")
        profile.pop("blockysize")
        profile["tiled"] = False
    grid = store.grid
    bstep = grid.step // step  # block step in output samples
    fill = _fill_value(dtype, nodata)
    try:
        dst = rasterio.open(out, "w", **profile)
    except rasterio.errors.RasterioIOError as exc:
        raise StoreError(f"cannot write {str(out)!r}: {exc}") from exc
    with dst:
        _write_vertical(dst, store)
        for br in range(grid.rows):
            r0 = br * bstep
            nrows = min(bstep + 1, height - r0)
            band = np.full((nrows, width), fill, dtype=dtype)
            for bc in range(grid.cols):
                c0 = bc * bstep
                ncols = min(bstep + 1, width - c0)
                if not store.index.exists[br, bc]:
                    continue
                g = stored_block(store, (br, bc), level)[:nrows, :ncols]
                if store.index.has_nodata[br, bc]:
                    valid = store.read_mask((br, bc))[::step, ::step][:nrows, :ncols]
                    g = np.where(valid, g, fill)
                band[:, c0 : c0 + ncols] = g
            dst.write(band, 1, window=Window(0, r0, width, nrows))
            if progress:
                progress(br + 1, grid.rows)


def stored_block(store: TerrainStore, block: tuple[int, int], level: int) -> np.ndarray:
    """A block's grid at ``level`` in the source dtype, before any vertical scale/offset (the
    integers a scaled DEM stores; ``read_block`` gives metres)."""
    raws = store.read_levels_raw(block, level)
    values = decode_grid(raws, store.meta.value_dtype, level)
    if store.meta.precision:
        return dequantise(values, store.meta.precision, store.dtype)
    return values.astype(store.dtype, copy=False)


def _write_vertical(dst: rasterio.io.DatasetWriter, store: TerrainStore) -> None:
    """Carry the band's scale/offset and units over, so the export reads as the source did."""
    v = store.meta.extra.get("vertical")
    if v:
        dst.scales = (float(v["scale"]),)
        dst.offsets = (float(v["offset"]),)
    if store.meta.vertical_units:
        dst.units = (store.meta.vertical_units,)


def _fill_value(dtype: np.dtype, nodata: float | None):
    if nodata is None:
        return np.zeros((), dtype=dtype)[()]
    return np.asarray(nodata).astype(dtype)[()]
