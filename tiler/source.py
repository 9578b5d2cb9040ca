"""Source reading for the tiler: open a raster, derive the store metadata, read block windows."""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING

import numpy as np
import rasterio
import rasterio.errors
from rasterio.windows import Window

from tiler import static_error
from tiler.encoding import encoding_for, parse_dtype, storage_dtype_for
from tiler.errors import SourceError, SourceNotFoundError
from tiler.grid import BlockGrid
from tiler.store import StoreMeta, is_url, tool_version

if TYPE_CHECKING:
    from tiler.tile import TileOptions

log = logging.getLogger("tiler.tile")


def _open_source(src: str | os.PathLike, band: int) -> rasterio.DatasetReader:
    path = str(src)
    if not is_url(path) and not path.startswith("/vsi") and not os.path.exists(path):
        raise SourceNotFoundError(f"source raster {path!r} does not exist")
    try:
        ds = rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise SourceError(f"cannot open {path!r} as a raster (GDAL says: {exc})") from exc
    if band > ds.count:
        ds.close()
        raise SourceError(f"band {band} does not exist: {path!r} has {ds.count} band(s)")
    return ds


def _source_meta(ds: rasterio.DatasetReader, src: str, opts: TileOptions) -> StoreMeta:
    if ds.height < 2 or ds.width < 2:
        raise SourceError(
            f"{src!r} is {ds.height}x{ds.width} samples; a DEM needs at least 2x2 to be tiled"
        )
    dtype = parse_dtype(ds.dtypes[opts.band - 1])
    if opts.precision and dtype.kind != "f":
        raise SourceError(
            f"--precision applies to float DEMs; {src!r} is {dtype.name}, which is stored "
            "losslessly already. Drop --precision."
        )
    value = np.dtype(np.int32) if opts.precision else dtype
    storage = storage_dtype_for(value)
    nodata = ds.nodatavals[opts.band - 1]
    k = opts.k
    cap = static_error.default_cap(k) if opts.error_cap is None else opts.error_cap
    if not 0 <= cap <= max(0, k - 1):
        raise SourceError(f"error cap must be in 0..{k - 1} for k={k}, got {cap}")
    t = ds.transform
    if ds.crs is not None and ds.crs.is_geographic:
        log.warning(
            "%s is in a geographic CRS: x and y are degrees while heights are metres, so "
            "streaming and rendering see a squashed DEM; reproject it to a projected CRS "
            "(e.g. gdalwarp -t_srs EPSG:32618) before tiling for those",
            src,
        )
    if abs(t.b) > 1e-12 * abs(t.a) or abs(t.d) > 1e-12 * abs(t.e):
        raise SourceError(f"{src!r} has a rotated geotransform {tuple(t)[:6]}; warp it north-up")
    units = ds.units[opts.band - 1] if ds.units else None
    size = os.path.getsize(src) if not is_url(src) and os.path.isfile(src) else None
    return StoreMeta(
        format_version=1,
        k=k,
        height=ds.height,
        width=ds.width,
        dtype=dtype.name,
        storage_dtype=storage.name,
        encoding=encoding_for(value),
        precision=opts.precision,
        nodata=None if nodata is None else float(nodata),
        crs_wkt=ds.crs.to_wkt() if ds.crs else None,
        geotransform=(t.a, t.b, t.c, t.d, t.e, t.f),
        vertical_units=units or None,
        source={"name": os.path.basename(src.rstrip("/")), "path": src, "size_bytes": size},
        tool_version=tool_version(),
        error_cap=cap,
        error_fields=static_error.FIELDS,
        compressor={"name": "blosc-zstd-shuffle", "level": opts.compression_level},
    )


def read_window(ds: rasterio.DatasetReader, band: int, grid: BlockGrid, br: int, bc: int):
    """The source samples of block ``(br, bc)`` that lie inside the DEM."""
    r0, c0, h, w = grid.block_window(br, bc)
    return ds.read(band, window=Window(c0, r0, w, h))
