"""Rebuild a GeoTIFF or a COG of the whole DEM from a store at any level, block row by block row.

COG overviews are the store's own coarser levels, not a resampling pass: overview ``j`` holds
level ``L - j``, i.e. every ``2**j``-th sample of the exported level, bit for bit.

Coarse-level georeferencing. A level keeps the *samples* (vertices) at rows and columns
``0, s, 2s, …`` (``s = 2**(k-L)``). :func:`export_geotiff` at a coarse level writes a transform
that keeps each kept sample's centre where it was in the source (pixel size ``s`` times
larger, origin moved by ``-(s-1)/2`` source pixels). Inside a COG, GDAL defines an overview's
georeferencing itself: the same extent as the full raster with ``s`` times larger pixels, so
overview pixel ``i`` is centred ``(s-1)/2`` source pixels right of (and below) the sample
``i*s`` it holds. That is at most half an overview pixel, the usual convention of
nearest-neighbour overviews (``gdaladdo -r nearest`` picks a sample off-centre too); for exact
positions at a coarse level use ``export_geotiff(level=L)`` or the xarray backend.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator

import numpy as np
import rasterio
import rasterio.errors
from rasterio.transform import Affine
from rasterio.windows import Window

from tiler.atomic import raster_written_whole
from tiler.encoding import dequantise
from tiler.errors import StoreError
from tiler.grid import as_index
from tiler.store import TerrainStore


@contextlib.contextmanager
def _written_whole(store: TerrainStore, out: str | os.PathLike) -> Iterator[str]:
    """A temporary path beside ``out`` to write to (:func:`tiler.atomic.raster_written_whole`):
    renamed to ``out`` once read back whole and the store found unchanged (a forced check: a
    remote store replaced meanwhile would mix two DEMs), else removed."""
    try:
        with raster_written_whole(out, lambda: store.check_unchanged(force=True)) as tmp:
            yield tmp
    except StoreError:
        raise
    except OSError as exc:  # (mkstemp's, or the raster that could not be read back)
        text = str(exc)
        raise StoreError(
            text if text.startswith("cannot write") else f"cannot write {str(out)!r}: {text}"
        ) from exc


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
    creation: dict | None = None,
) -> None:
    """Write the DEM at ``level`` (default finest) to a tiled GeoTIFF; nodata restored.
    ``creation`` overrides GDAL creation options (e.g. ``{"compress": "zstd"}``).

    At the finest level of a lossless store the samples are bit-identical to the source's, with
    the same CRS and transform. Coarser levels keep every ``2**(k-level)``-th sample, so the
    transform's pixel size grows by that factor (its origin stays on sample (0, 0)).
    """
    k = store.k
    level = k if level is None else as_index(level, "level")
    if not 0 <= level <= k:
        raise StoreError(
            "{level_param} must be in 0..{k} for this store, got {level}",
            params={"level_param": "level"},
            k=k,
            level=level,
        )
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
    if nodata is None and dtype.kind == "f" and _holes_inside(store):
        nodata = float("nan")  # (masked samples, NaN, with no value declared)
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
    profile.update(creation or {})
    with _written_whole(store, out) as path:
        _write_levels(store, path, profile, level, step, progress)


def _write_levels(
    store: TerrainStore,
    out: str,
    profile: dict,
    level: int,
    step: int,
    progress: Callable[[int, int], None] | None,
) -> None:
    """:func:`export_geotiff`'s writing to ``out`` (``profile``: its rasterio profile), block
    row by block row."""
    height, width = profile["height"], profile["width"]
    dtype, nodata = np.dtype(profile["dtype"]), profile["nodata"]
    grid = store.grid
    bstep = grid.step // step  # block step in output samples
    fill = _fill_value(dtype, nodata)
    m = store.meta
    try:
        dst = rasterio.open(out, "w", **profile)
    except rasterio.errors.RasterioIOError as exc:
        raise StoreError(f"cannot write {str(out)!r}: {exc}") from exc
    with dst:
        _write_vertical(dst, store)
        # (the transform read back is the same; a GeoTIFF without a CRS cannot say it without
        # GDAL inventing one, LOCAL_CS["unnamed"], which a re-tiling would then keep)
        if m.extra.get("area_or_point") == "Point" and m.crs_wkt:
            dst.update_tags(AREA_OR_POINT="Point")
        for br in range(grid.rows):
            r0 = br * bstep
            nrows = min(bstep + 1, height - r0)
            band = np.full((nrows, width), fill, dtype=dtype)
            for bc in range(grid.cols):
                c0 = bc * bstep
                ncols = min(bstep + 1, width - c0)
                if not store.index.exists[br, bc]:
                    continue
                g = stored_block(store, (br, bc), level, (nrows, ncols))
                if store.index.has_nodata[br, bc]:
                    valid = store.read_mask((br, bc))[::step, ::step][:nrows, :ncols]
                    g = np.where(valid, g, fill)
                band[:, c0 : c0 + ncols] = g
            dst.write(band, 1, window=Window(0, r0, width, nrows))
            if progress:
                progress(br + 1, grid.rows)


def stored_block(
    store: TerrainStore,
    block: tuple[int, int],
    level: int,
    extent: tuple[int, int] | None = None,
) -> np.ndarray:
    """A block's grid at ``level`` in the source dtype, before any vertical scale/offset (the
    integers a scaled DEM stores; ``read_block`` gives metres); ``extent``: its top-left part
    only (see ``read_block``)."""
    raws = store.read_levels_raw(block, level)
    values = store.codec.decode_grid(raws, level, extent)
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


def _holes_inside(store: TerrainStore) -> bool:
    """True if the DEM has masked samples (the padding past its edge is not one)."""
    from tiler.info import blocks_with_nodata

    return not bool(store.index.exists.all()) or blocks_with_nodata(store) > 0


def _fill_value(dtype: np.dtype, nodata: float | None):
    if nodata is None:
        return np.zeros((), dtype=dtype)[()]
    return np.asarray(nodata).astype(dtype)[()]


COG_BLOCK = 512  # COG tile edge; overviews are added until the level fits one tile
_GDAL_TYPES = {
    "uint8": "Byte",
    "int8": "Int8",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "float32": "Float32",
    "float64": "Float64",
}


def cog_levels(store: TerrainStore, level: int) -> list[int]:
    """Store levels a COG of ``level`` holds: ``level`` then coarser ones, down to the first
    whose raster fits one ``COG_BLOCK`` tile."""
    out = [level]
    while out[-1] > 0 and max(export_shape(store, out[-1])[:2]) > COG_BLOCK:
        out.append(out[-1] - 1)
    return out


def export_cog(
    store: TerrainStore,
    out: str | os.PathLike,
    level: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    tmpdir: str | os.PathLike | None = None,
) -> list[int]:
    """Write the DEM at ``level`` (default finest) as a Cloud Optimized GeoTIFF whose overviews
    are the store's coarser levels (see the module doc); return the levels it holds.

    Each level is first written to a temporary tiled GeoTIFF (in ``tmpdir``, by default beside
    ``out``; about 1.33x the output's raw size), then GDAL's COG driver assembles them.
    """
    from xml.sax.saxutils import escape

    import rasterio.shutil

    k = store.k
    level = k if level is None else as_index(level, "level")
    if not 0 <= level <= k:
        raise StoreError(
            "{level_param} must be in 0..{k} for this store, got {level}",
            params={"level_param": "level"},
            k=k,
            level=level,
        )
    levels = cog_levels(store, level)
    total = sum(store.grid.rows for _ in levels)
    done = 0

    def step_progress(i: int, n: int) -> None:
        if progress:
            progress(done + i, total)

    where = tmpdir or os.path.dirname(os.path.abspath(out))
    try:
        tmp = tempfile.TemporaryDirectory(prefix=".terrastream-cog-", dir=where)
    except OSError as exc:
        raise StoreError(f"cannot write temporary files in {str(where)!r}: {exc}") from exc
    with tmp as d:
        paths = []
        fast = {"compress": "zstd", "zstd_level": 1, "predictor": 1}
        for lv in levels:
            path = os.path.join(d, f"level_{lv}.tif")
            export_geotiff(store, path, lv, step_progress, creation=fast)
            done += store.grid.rows
            paths.append(path)
        with rasterio.open(paths[0]) as full:
            width, height = full.width, full.height
            nodata = full.nodata
            gt = full.transform.to_gdal()
            crs_wkt = full.crs.to_wkt() if full.crs else None
        dtype = np.dtype(store.meta.dtype)
        band = [f'<VRTRasterBand dataType="{_GDAL_TYPES[dtype.name]}" band="1">']
        if nodata is not None:
            band.append(f"<NoDataValue>{_xml_number(nodata)}</NoDataValue>")
        v = store.meta.extra.get("vertical")
        if v:
            band.append(
                f"<Offset>{float(v['offset'])!r}</Offset><Scale>{float(v['scale'])!r}</Scale>"
            )
        if store.meta.vertical_units:
            band.append(f"<UnitType>{escape(store.meta.vertical_units)}</UnitType>")
        band.append(
            f"<SimpleSource><SourceFilename>{escape(paths[0])}</SourceFilename>"
            f"<SourceBand>1</SourceBand>"
            f'<SrcRect xOff="0" yOff="0" xSize="{width}" ySize="{height}"/>'
            f'<DstRect xOff="0" yOff="0" xSize="{width}" ySize="{height}"/></SimpleSource>'
        )
        for p in paths[1:]:
            band.append(
                f"<Overview><SourceFilename>{escape(p)}</SourceFilename>"
                "<SourceBand>1</SourceBand></Overview>"
            )
        band.append("</VRTRasterBand>")
        xml = [f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">']
        if store.meta.extra.get("area_or_point") == "Point" and crs_wkt:  # (as above)
            xml.append('<Metadata><MDI key="AREA_OR_POINT">Point</MDI></Metadata>')
        if crs_wkt:
            xml.append(f"<SRS>{escape(crs_wkt)}</SRS>")
        xml.append(f"<GeoTransform>{', '.join(repr(float(x)) for x in gt)}</GeoTransform>")
        xml += band
        xml.append("</VRTDataset>")
        vrt = os.path.join(d, "cog.vrt")
        with open(vrt, "w", encoding="utf-8") as f:
            f.write("\n".join(xml))
        try:
            with _written_whole(store, out) as path:
                rasterio.shutil.copy(
                    vrt,
                    path,
                    driver="COG",
                    BLOCKSIZE=COG_BLOCK,
                    COMPRESS="DEFLATE",
                    PREDICTOR="YES",
                    OVERVIEWS="FORCE_USE_EXISTING",
                    BIGTIFF="IF_SAFER",
                )
        except rasterio.errors.RasterioError as exc:
            raise StoreError(f"cannot write the COG {str(out)!r}: {exc}") from exc
    return levels


def _xml_number(v: float) -> str:
    return "nan" if np.isnan(v) else repr(float(v))
