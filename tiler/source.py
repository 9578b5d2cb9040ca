"""Source reading for the tiler: plan the sources, derive the store metadata, read block windows.

A source is one raster or many (a mosaic, see :mod:`tiler.mosaic`), optionally reprojected to
a target CRS while it is read. :func:`plan_source` turns what the user gave into a picklable
:class:`~tiler.mosaic.MosaicSpec` that every worker re-opens with :func:`open_source`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import rasterio
from rasterio.windows import Window

from tiler import static_error
from tiler.crs import crs_name, is_geographic, non_metre_unit
from tiler.encoding import encoding_for, storage_dtype_for
from tiler.errors import SourceError
from tiler.grid import BlockGrid
from tiler.mosaic import MosaicReader, MosaicSpec, plan_mosaic
from tiler.schema import COMPRESSOR_NAME, bitshuffle_levels, sparse_byte_shuffle
from tiler.store import StoreMeta, tool_version
from tiler.vertical import vertical_meta

if TYPE_CHECKING:
    from tiler.tile import TileOptions

log = logging.getLogger("tiler.tile")

SourceLike = str | os.PathLike | Sequence[str | os.PathLike] | MosaicSpec


def read_source_list(path: str | os.PathLike) -> list[str]:
    """Paths listed one per line in a text file (blank lines and ``#`` comments skipped).

    Relative paths are taken relative to the list file's folder.
    """
    path = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            lines = f.read().splitlines()
    except OSError as exc:
        raise SourceError(f"cannot read the source list {path!r}: {exc}") from exc
    except UnicodeDecodeError as exc:  # (a DEM given as the list: `--from-list dem.tif`)
        raise SourceError(
            f"the source list {path!r} (--from-list) is not a UTF-8 text file (byte "
            f"{exc.start}: {exc.reason}); give a text file naming one source per line, or "
            "give the raster itself as a SRC argument"
        ) from None
    base = os.path.dirname(os.path.abspath(path))
    out = []
    for line in lines:
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        out.append(s if "://" in s or s.startswith("/") else os.path.join(base, s))
    if not out:
        raise SourceError(f"the source list {path!r} names no rasters")
    return out


def plan_source(src: SourceLike, opts: TileOptions) -> MosaicSpec:
    """The picklable plan of the source(s) for ``opts`` (target CRS, resolution, resampling)."""
    if isinstance(src, MosaicSpec):
        return src
    paths = [str(src)] if isinstance(src, str | os.PathLike) else [str(p) for p in src]
    return plan_mosaic(
        paths,
        band=opts.band,
        dst_crs=opts.dst_crs,
        resolution=opts.resolution,
        resampling=opts.resampling,
    )


def open_source(src: SourceLike, band: int) -> MosaicReader:
    """A window reader over the planned source(s); close it (or use ``with``) when done."""
    if not isinstance(src, MosaicSpec):
        paths = [str(src)] if isinstance(src, str | os.PathLike) else [str(p) for p in src]
        src = plan_mosaic(paths, band=band)
    return MosaicReader(src)


def source_label(spec: MosaicSpec) -> dict:
    """The ``source`` entry of the store metadata: name, path(s), total size."""
    first = spec.sources[0]
    n = len(spec.sources)
    sizes = [s.size_bytes for s in spec.sources]
    out = {
        "name": os.path.basename(first.path.rstrip("/")) + (f" + {n - 1} more" if n > 1 else ""),
        "path": first.path,
        "size_bytes": None if None in sizes else sum(sizes),
    }
    if n > 1:
        out["paths"] = [s.path for s in spec.sources]
    return out


def source_meta(ds: MosaicReader, src: SourceLike, opts: TileOptions) -> StoreMeta:
    """The store metadata a tiling of ``ds`` with ``opts`` writes (before its job identity)."""
    spec = ds.spec
    label = source_label(spec)["name"]
    dtype = np.dtype(spec.dtype)
    if opts.precision and dtype.kind != "f":
        raise SourceError(
            "{precision} applies to float DEMs; {label!r} is {dtype}, which is stored "
            "losslessly already. Drop {precision}.",
            params={"precision": "precision"},
            label=label,
            dtype=dtype.name,
        )
    value = np.dtype(np.int32) if opts.precision else dtype
    storage = storage_dtype_for(value)
    k = opts.k
    cap = static_error.default_cap(k) if opts.error_cap is None else opts.error_cap
    if not 0 <= cap <= max(0, k - 1):
        raise SourceError(f"error cap must be in 0..{k - 1} for k={k}, got {cap}")
    if is_geographic(spec.crs_wkt):
        log.warning(
            "%s is in a geographic CRS (%s): x and y are degrees while heights are metres; the "
            "store is lossless but cannot be streamed or rendered. Reproject while tiling with "
            "a target CRS ('auto' picks the UTM zone) for those.",
            label,
            crs_name(spec.crs_wkt),
        )
    unit = non_metre_unit(spec.crs_wkt)
    if unit is not None:
        log.warning(
            "%s is in %s, whose x and y are in %s while heights are metres; the store is "
            "lossless but cannot be streamed or rendered. Reproject while tiling with a target "
            "CRS in metres ('auto' picks the UTM zone) for those.",
            label,
            crs_name(spec.crs_wkt),
            unit[0],
        )
    first = spec.sources[0]
    extra: dict = {"source_crs_wkt": spec.source_crs_wkt}
    if spec.warp:
        extra["reprojection"] = {
            "requested": "auto" if spec.dst_crs == "auto" else crs_name(spec.dst_crs),
            "crs": crs_name(spec.crs_wkt),
            "resampling": spec.resampling,
            "resolution": [spec.transform[0], -spec.transform[4]],
        }
        names = list(dict.fromkeys(crs_name(i.crs_wkt) for i in spec.sources))
        if len(names) > 1:  # (source_crs_wkt is the first source's)
            extra["source_crss"] = names
    vertical = vertical_meta(first.scale, first.offset, first.units)
    if vertical:
        if opts.precision:
            raise SourceError(
                "{precision} with a band scale/offset or vertical units other than metres "
                "({vertical}) is not supported for {label!r}; drop {precision} (the heights "
                "are then stored losslessly)",
                params={"precision": "precision"},
                vertical=vertical,
                label=label,
            )
        extra["vertical"] = vertical
    if len(spec.sources) > 1:
        extra["mosaic"] = {"count": len(spec.sources), "overlap_rule": "first-valid"}
    if not spec.warp and all(i.area_or_point == "Point" for i in spec.sources):
        extra["area_or_point"] = "Point"  # what export writes back (SRTM, many DEMs)
    return StoreMeta(
        format_version=1,
        k=k,
        height=spec.height,
        width=spec.width,
        dtype=dtype.name,
        storage_dtype=storage.name,
        encoding=encoding_for(value),
        precision=opts.precision,
        nodata=spec.nodata,
        crs_wkt=spec.crs_wkt,
        geotransform=spec.transform,
        vertical_units=first.units,
        source=source_label(spec),
        tool_version=tool_version(),
        error_cap=cap,
        error_fields=static_error.FIELDS,
        compressor=compressor_meta(encoding_for(value), k, opts.compression_level),
        extra=extra,
    )


def compressor_meta(encoding: str, k: int, level: int) -> dict[str, object]:
    """``meta.compressor`` of a new store: name, zstd level, the bit-shuffled levels and, where
    there are any, the sparse-block rule (:func:`tiler.schema.sparse_byte_shuffle`)."""
    out: dict[str, object] = {
        "name": COMPRESSOR_NAME,
        "level": level,
        "bitshuffle_levels": bitshuffle_levels(encoding, k),
    }
    rule = sparse_byte_shuffle(encoding, k)
    if rule is not None:
        out["sparse_byte_shuffle"] = rule
    return out


def read_window(
    ds: MosaicReader | rasterio.DatasetReader, band: int, grid: BlockGrid, br: int, bc: int
) -> np.ndarray:
    """The source samples of block ``(br, bc)`` that lie inside the DEM."""
    r0, c0, h, w = grid.block_window(br, bc)
    return ds.read(band, window=Window(c0, r0, w, h))


def check_source_options(opts: TileOptions) -> None:
    """Validate the source options of ``TileOptions`` (target CRS, resampling, resolution)."""
    from tiler.crs import parse_dst_crs, parse_resampling

    if opts.dst_crs is not None:
        parse_dst_crs(opts.dst_crs)
    parse_resampling(opts.resampling)
    if opts.resolution is not None:
        if opts.dst_crs is None:
            raise SourceError(
                f"a resolution ({opts.resolution}) applies when reprojecting; give a target CRS"
            )
        r = opts.resolution
        if not (isinstance(r, int | float) and np.isfinite(r) and r > 0):
            raise SourceError(f"resolution must be a positive number of target units, got {r}")
