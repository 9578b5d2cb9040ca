"""``terrastream info``: a store's description as a plain dict (no printing here)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from tiler.crs import crs_name, is_geographic, non_metre_unit
from tiler.layout import level_size
from tiler.store import TerrainStore, open_store
from tiler.vertical import height_transform


def raster_bounds(geotransform: Any, height: int, width: int) -> list[float]:
    """``(left, bottom, right, top)`` of the raster's pixel edges (rasterio's ``bounds``) from
    the store's geotransform (Affine order): half a cell beyond the sample centres of
    ``BlockGrid.extent``."""
    from rasterio.transform import Affine, array_bounds

    west, south, east, north = array_bounds(height, width, Affine(*geotransform))
    return [float(west), float(south), float(east), float(north)]


def store_info(url: str | os.PathLike) -> dict[str, Any]:
    """Blocks, levels, bytes per level and component, ratio to raw, CRS, extent, value range."""
    s = open_store(url)
    m = s.meta
    idx = s.index
    # sizes: None where the store's files cannot be listed (an http(s) server), not 0
    listed = s.location.can_list
    nbytes = s.nbytes() if listed else None
    per_level = s.level_nbytes() if listed else [None] * (m.k + 1)
    raw = m.height * m.width * np.dtype(m.dtype).itemsize
    # EPSG:n, else the PROJ string, whole (a WKT cut at 80 characters could not be parsed);
    # None without a CRS
    crs = crs_name(m.crs_wkt) if m.crs_wkt else None
    vr = m.extra.get("value_range", [float("nan"), float("nan")])
    vertical = m.extra.get("vertical")
    a, b = height_transform(m)
    stored_range = sorted([(vr[0] - b) / a, (vr[1] - b) / a]) if vertical else None
    return {
        "url": s.url,
        "format_version": m.format_version,
        "tool_version": m.tool_version,
        "source": m.source.get("name"),
        "checksum": m.source.get("checksum"),
        "height": m.height,
        "width": m.width,
        "dtype": m.dtype,
        "precision": m.precision,
        "nodata": m.nodata,
        "block_size": m.block_size,
        "block_rows": s.grid.rows,
        "block_cols": s.grid.cols,
        "blocks_with_terrain": int(idx.exists.sum()),
        "blocks_with_nodata": blocks_with_nodata(s),
        "levels": m.levels,
        "encoding": m.encoding,
        "checksums": "crc32c on every chunk"
        if m.checksummed
        else f"none (format {m.format_version})",
        "generation": m.generation,
        "compressor": compressor_text(m.compressor),
        "crs": crs,
        "extent": list(s.grid.extent),  # sample centres (xmin, ymin, xmax, ymax)
        "bounds": raster_bounds(m.geotransform, m.height, m.width),  # pixel edges, as GDAL
        "value_range": vr,
        "vertical_units": m.vertical_units,
        # heights: value_range is in metres; the stored values are (metres - offset) / scale
        "vertical": vertical,  # {"scale", "offset", "units", "metres_per_unit"} or None
        "value_range_stored": stored_range,
        "source_crs": " + ".join(m.extra["source_crss"])  # a mosaic warped from several
        if m.extra.get("source_crss")
        else crs_name(m.extra.get("source_crs_wkt"))
        if m.extra.get("source_crs_wkt")
        else crs,
        "reprojection": m.extra.get("reprojection"),  # {"requested", "crs", ...} or None
        "crs_geographic": is_geographic(m.crs_wkt),
        "crs_unit": (non_metre_unit(m.crs_wkt) or (None,))[0],  # x/y's unit when not metres
        "sources": m.extra.get("mosaic", {}).get("count", 1),
        "bytes_per_level": [
            {"level": i, "values_per_block": level_size(i), "bytes": b}
            for i, b in enumerate(per_level)
        ],
        "bytes": nbytes,
        "raw_bytes": raw,
        "ratio_to_raw": nbytes["total"] / raw if nbytes else None,
    }


def blocks_with_nodata(store: TerrainStore) -> int:
    """Blocks holding nodata samples inside the DEM (padding beyond the DEM edge is not nodata)."""
    idx = store.index
    grid = store.grid
    n = 0
    for br, bc in zip(*np.nonzero(idx.has_nodata & idx.exists), strict=True):
        _, _, h, w = grid.block_window(int(br), int(bc))
        if h == grid.side and w == grid.side:
            n += 1  # an interior block: its masked samples are nodata
        elif not store.read_mask((int(br), int(bc)))[:h, :w].all():
            n += 1
    return n


def compressor_text(compressor: dict[str, Any]) -> str:
    """``meta.compressor`` in words: name, level, the bit-shuffled levels if any and the
    sparse-block rule if recorded."""
    text = f"{compressor.get('name')} level {compressor.get('level')}"
    bits = compressor.get("bitshuffle_levels") or []
    if bits:
        text += f", levels {', '.join(str(i) for i in bits)} bit shuffled"
    rule = compressor.get("sparse_byte_shuffle")
    if bits and isinstance(rule, dict):
        text += (
            f" (byte shuffled in blocks at most {rule.get('terrain_max', 0):.0%} terrain where "
            f"at most {rule.get('slack', 1) - 1:.0%} larger)"
        )
    return text
