"""One source raster's header, read and checked: what the mosaic needs to place and read it
(:class:`SourceInfo`, :func:`read_info`), and the refusals and warnings a file's own
declarations call for (no geotransform, a nodata no sample can take, a colour band)."""

from __future__ import annotations

import logging
import math
import os
import re
import warnings
from dataclasses import dataclass

import numpy as np
import rasterio
import rasterio.errors
from rasterio.enums import ColorInterp, MaskFlags

from tiler.crs import vertical_crs_unit
from tiler.encoding import parse_dtype
from tiler.errors import SourceError, SourceNotFoundError, SourceUnavailableError
from tiler.source_http import (
    forget_failed_open,
    gdal_network_failure,
    http_url,
    is_remote,
    is_s3,
    remote_env,
    server_failure,
    slow_advice,
)
from tiler.store import is_url

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SourceInfo:
    """One source raster's header: what the mosaic needs to place and read it."""

    path: str
    width: int
    height: int
    transform: tuple[float, float, float, float, float, float]  # Affine order a..f
    crs_wkt: str | None
    dtype: str
    nodata: float | None
    scale: float
    offset: float
    units: str | None
    size_bytes: int | None
    footprint: tuple[int, int, int, int] = (0, 0, 0, 0)  # row0, col0, row1, col1 on the target
    # when reprojecting: the hull of the source's sample centres in target coordinates (a ring)
    hull: tuple[tuple[float, float], ...] = ()
    # GDAL marks the band's invalid samples by a mask (a per-dataset mask or an alpha band)
    masked: bool = False
    # GDAL's AREA_OR_POINT ("Area", "Point" or None): how its samples are meant (GDAL's
    # geotransform is the pixel corners' either way)
    area_or_point: str | None = None
    # when reprojecting: the indices (in the spec) of the other sources whose footprint meets
    # this one's: the seam between two tiles that share no sample lies outside both hulls,
    # and MosaicReader fills it from rings round them (tiler.mosaic_plan.seam_rings, built
    # by the reader, not shipped with every block task). Derived from the fields above, so
    # not in a resume fingerprint (tiler.resume: the fields before ``masked``)
    near: tuple[int, ...] = ()


#: GDAL's connection strings naming a part of a file: ``NETCDF:"f.nc":elevation``,
#: ``HDF5:"f.h5"://grp/dem``, ``GTIFF_DIR:2:f.tif``
_GDAL_SUBDATASET = re.compile(r"^[A-Za-z][A-Za-z0-9_]+:(?!//)")  # (rasterio lists netcdf:...)


def is_file_path(path: str) -> bool:
    """True if ``path`` names a file on this machine (not a URL, a ``/vsi...`` path or a GDAL
    subdataset such as ``NETCDF:"f.nc":elevation``): one whose absence can be told at once."""
    text = str(path)
    return not (is_url(text) or text.startswith("/vsi") or _GDAL_SUBDATASET.match(text))


def open_raster(path: str) -> rasterio.DatasetReader:
    """Open a source raster with rasterio (a remote one with
    :func:`~tiler.source_http.remote_env`'s time limits); a missing file or one GDAL cannot
    read is a :class:`SourceError` naming the path, a URL whose server failed a
    :class:`SourceUnavailableError` (:func:`_open_failed`)."""
    if is_file_path(path) and not os.path.exists(path):
        raise SourceNotFoundError(f"source raster {path!r} does not exist")
    try:
        with warnings.catch_warnings(), remote_env(path):
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            return rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        if is_remote(path):
            forget_failed_open()  # (else a second open says "does not exist" unasked)
        raise _open_failed(path, exc) from exc


def _open_failed(path: str, exc: Exception) -> SourceError:
    """The error for GDAL failing to open ``path``: for an ``http(s)`` URL the server is asked
    why first (GDAL reports a server's 503 or silence as "not recognized as being in a
    supported file format")."""
    url = http_url(path)
    failure = server_failure(url) if url else None
    if failure is None and not url and is_remote(path):
        return _network_failed(path, exc) or SourceError(
            f"cannot open {path!r} as a raster (GDAL says: {exc})"
        )
    if failure is None:
        return SourceError(f"cannot open {path!r} as a raster (GDAL says: {exc})")
    what, status = failure
    if status in (404, 410):
        return SourceNotFoundError(f"source raster {path!r} does not exist: its server {what}")
    if status in (401, 403):  # (asked without GDAL's credentials, if it has any)
        what += " to a request without credentials"
        todo = (
            "access was refused, not the file damaged: check the URL's credentials or "
            "GDAL's (GDAL_HTTP_AUTH, GDAL_HTTP_HEADERS...), and try again"
        )
    else:
        todo = "the server or the network failed, not the file: check them and try again"
        todo += slow_advice(what)
    return SourceUnavailableError(f"cannot open source {path!r}: its server {what}; {todo}")


def _network_failed(path: str, exc: Exception) -> SourceUnavailableError | None:
    """For a network path no plain GET can ask about (``s3://``, ``/vsis3/``... : signed
    requests), the error GDAL's own words call for: a server or network that failed, or
    refused the credentials, is :class:`SourceUnavailableError` (None: anything else)."""
    said = str(exc)
    kind = gdal_network_failure(said)
    if kind is None:
        return None
    where = ""
    if is_s3(path):
        endpoint = os.environ.get("AWS_S3_ENDPOINT") or os.environ.get("AWS_ENDPOINT_URL_S3")
        endpoint = endpoint or os.environ.get("AWS_ENDPOINT_URL")
        where = (
            f" (S3 endpoint {endpoint!r}: AWS_ENDPOINT_URL, or GDAL's AWS_S3_ENDPOINT/"
            "AWS_HTTPS/AWS_VIRTUAL_HOSTING)"
            if endpoint
            else " (AWS's own endpoint; an S3-compatible server is named by AWS_ENDPOINT_URL)"
        )
    if kind == "refused":
        todo = (
            "access was refused, not the file damaged: check the credentials (AWS_ACCESS_KEY_ID"
            "/AWS_SECRET_ACCESS_KEY, AWS_PROFILE, or AWS_NO_SIGN_REQUEST=YES for a public "
            "bucket) and try again"
            if is_s3(path)
            else "access was refused, not the file damaged: check GDAL's credentials and try again"
        )
        return SourceUnavailableError(
            f"cannot open source {path!r}: its server refused access{where} (GDAL says: {said}); "
            f"{todo}"
        )
    return SourceUnavailableError(
        f"cannot open source {path!r}: GDAL could not get it from its server{where} (GDAL "
        f"says: {said}); the server or the network failed, not the file: check the server, "
        "the endpoint and the network, and try again"
    )


def _check_georeferenced(ds: rasterio.DatasetReader, path: str) -> None:
    """Refuse a raster without a geotransform (GDAL's identity, with or without a CRS: a CRS
    alone places nothing), naming what it has instead (ground control points, RPCs or
    nothing) and how to put it on a grid; and a geotransform that is not finite."""
    if not all(math.isfinite(v) for v in tuple(ds.transform)[:6]):
        raise SourceError(
            f"{path!r} has a geotransform that is not finite {tuple(ds.transform)[:6]}; fix it "
            "(`gdal_edit.py -a_ullr ULX ULY LRX LRY`) and tile it again"
        )
    if not ds.transform.is_identity:
        return
    name = os.path.basename(path.rstrip("/"))
    gcps, gcp_crs = ds.gcps
    if gcps:
        srs = f"EPSG:{gcp_crs.to_epsg()}" if gcp_crs and gcp_crs.to_epsg() else "<CRS>"
        raise SourceError(
            f"{path!r} is georeferenced by {len(gcps)} ground control points, not a "
            f"geotransform; warp it onto a grid first, e.g. `gdalwarp -t_srs {srs} {name} "
            "grid.tif`, and tile that"
        )
    if ds.rpcs:
        raise SourceError(
            f"{path!r} is georeferenced by RPCs, not a geotransform; orthorectify it onto a "
            f"grid first, e.g. `gdalwarp -rpc -t_srs <CRS> {name} grid.tif`, and tile that"
        )
    if ds.crs is not None:
        raise SourceError(
            f"{path!r} has a CRS but no geotransform (GDAL's identity: no position on the "
            "ground, rows running south); give it its corners first, e.g. `gdal_translate "
            f"-a_ullr ULX ULY LRX LRY {name} grid.tif`, and tile that"
        )
    raise SourceError(
        f"{path!r} is not georeferenced (no geotransform, ground control points or RPCs); "
        f"give it a grid first, e.g. `gdal_translate -a_ullr 0 {ds.height} {ds.width} 0 {name} "
        "grid.tif` for one unit per sample (add -a_srs <CRS> for a CRS), and tile that"
    )


def _warn_colour(path: str, band: int, interp: ColorInterp) -> None:
    """Warn when the band GDAL names a colour (a palette's indices, an RGB image's channel):
    its values are tiled as heights all the same."""
    colours = {ColorInterp.palette: "a palette's colour indices"}
    for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha):
        colours[c] = f"the {c.name} channel of an image"
    what = colours.get(interp)
    if what is not None:
        log.warning(
            "band %d of %r holds %s, not heights as far as GDAL knows; it is tiled as heights "
            "(a DEM is one band of heights: check the file, or choose the band)",
            band,
            path,
            what,
        )


def _check_nodata(path: str, dtype: str, nodata: float | None) -> None:
    """Refuse an integer band whose declared nodata no sample can take (a fraction; rasterio
    already drops NaN and out-of-range ones): GDAL then reads none as nodata, while casting it
    would hide another value."""
    dt = np.dtype(dtype)
    if nodata is None or dt.kind not in "iu" or not math.isfinite(nodata):
        return
    info = np.iinfo(dt)
    inside = info.min <= nodata <= info.max
    if nodata != math.floor(nodata) or not inside:
        cast = f", cast to {dt.name} it would hide the samples equal to {int(nodata)}"
        raise SourceError(
            f"{path!r} declares nodata {nodata:g} for its {dt.name} samples, which none can "
            f"take (GDAL reads none as nodata{cast if inside else ''}); fix the declaration: "
            "`gdal_edit.py -a_nodata V` with the value its nodata samples hold, or "
            "`-unsetnodata` (a file you cannot edit: `gdal_translate -of VRT -a_nodata V` "
            "and tile the VRT)"
        )


def read_info(path: str, band: int) -> SourceInfo:
    """Header of one source (opened and closed again)."""
    with remote_env(path):  # (the header asks for side files: .msk, .aux.xml)
        return _read_info(path, band)


def _read_info(path: str, band: int) -> SourceInfo:
    with open_raster(path) as ds:
        if ds.count == 0:  # GDAL opened it (a zarr store, a vector file...) but as no raster
            if os.path.isfile(os.path.join(path, "zarr.json")):
                raise SourceError(
                    f"{path!r} is a zarr store, not a DEM (a terrastream store is tiled "
                    f"already: `terrastream export {path} dem.tif` rebuilds its DEM); give the "
                    "source DEM"
                )
            if ds.subdatasets:  # a netCDF/HDF file of several variables
                subs = ds.subdatasets
                listed = ", ".join(subs[:6]) + (" ..." if len(subs) > 6 else "")
                raise SourceError(
                    f"{path!r} holds {len(subs)} rasters, not one; give the DEM's as GDAL "
                    f"names it: {listed}"
                )
            raise SourceError(
                f"{path!r} has no raster bands (GDAL's {ds.driver} driver opened it); give a "
                "DEM raster"
            )
        if band > ds.count:
            raise SourceError(f"band {band} does not exist: {path!r} has {ds.count} band(s)")
        if ds.count > 1:
            log.warning(
                "%r has %d bands; band %d is read as the heights (tile --band chooses another)",
                path,
                ds.count,
                band,
            )
        if ds.height < 2 or ds.width < 2:
            raise SourceError(
                f"{path!r} is {ds.height}x{ds.width} samples; a DEM needs at least 2x2"
            )
        t = ds.transform
        _check_georeferenced(ds, path)
        nodata = ds.nodatavals[band - 1]
        _check_nodata(path, ds.dtypes[band - 1], nodata)
        flags = ds.mask_flag_enums[band - 1]
        _warn_colour(path, band, ds.colorinterp[band - 1])
        # the band's units, else the vertical part of a compound CRS (NAVD88 height in feet)
        units = (ds.units[band - 1] if ds.units else None) or vertical_crs_unit(ds.crs)
        size = os.path.getsize(path) if not is_url(path) and os.path.isfile(path) else None
        return SourceInfo(
            path=path,
            width=ds.width,
            height=ds.height,
            transform=(t.a, t.b, t.c, t.d, t.e, t.f),
            crs_wkt=ds.crs.to_wkt() if ds.crs else None,
            dtype=parse_dtype(ds.dtypes[band - 1]).name,
            nodata=None if nodata is None else float(nodata),
            scale=float(ds.scales[band - 1]) if ds.scales else 1.0,
            offset=float(ds.offsets[band - 1]) if ds.offsets else 0.0,
            units=units or None,
            size_bytes=size,
            # a per-dataset mask, an alpha band or the band's own mask band (GDAL's flags are
            # then none of all-valid and nodata); a nodata value is applied as nodata
            masked=MaskFlags.all_valid not in flags and MaskFlags.nodata not in flags,
            area_or_point=ds.tags().get("AREA_OR_POINT"),
        )
