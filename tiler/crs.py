"""Choosing a metric CRS for a DEM and refusing stores whose x/y are degrees.

Streaming and rendering treat x, y and z as one metric frame, so a store in a geographic CRS
(degrees) draws a squashed, meaningless surface. Tiling can reproject on the fly (see
:mod:`tiler.mosaic`); :func:`auto_crs` picks the target: the UTM zone of the data's centre when
the whole extent lies within that zone widened by :data:`UTM_MARGIN_DEG` on each side (and
within UTM's latitudes), otherwise an azimuthal equidistant projection centred on the data.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.errors import CRSError
from rasterio.warp import transform, transform_bounds

from tiler.errors import GeographicStoreError, SourceError
from tiler.vertical import require_heights

log = logging.getLogger(__name__)

UTM_MARGIN_DEG = 1.0  # how far past its 6-degree zone an extent may reach and still use UTM
#: the largest stretch of distances across (the azimuthal projection's scale factor at the
#: DEM's farthest point) that ``auto`` chooses without a warning, and beyond which it refuses
AUTO_STRETCH_WARN = 1.01
AUTO_STRETCH_MAX = 1.10
EARTH_RADIUS_M = 6_371_008.8  # the mean radius (IUGG)
UTM_LAT_RANGE = (-80.0, 84.0)
AUTO = "auto"
RESAMPLINGS = ("nearest", "bilinear", "cubic", "cubic_spline", "lanczos", "average")


def parse_dst_crs(value: str) -> str:
    """Validate a target CRS: ``"auto"``, an ``EPSG:…`` code, a PROJ string or WKT.

    Returns ``"auto"`` or the WKT of the CRS; raises ``SourceError`` naming the value otherwise.
    """
    text = str(value).strip()
    if text.lower() == AUTO:
        return AUTO
    try:
        with rasterio.Env():  # GDAL's errors to logging, not an "ERROR 1: PROJ: ..." on stderr
            crs = CRS.from_user_input(text)
    except CRSError as exc:
        raise SourceError(
            f"target CRS {value!r} is not understood ({exc}); give 'auto', an EPSG code such "
            "as 'EPSG:32619', a PROJ string or WKT"
        ) from exc
    if crs.is_geographic:
        raise SourceError(
            f"target CRS {value!r} is geographic (degrees); choose a projected CRS in metres, "
            "or 'auto'"
        )
    unit = non_metre_unit(crs.to_wkt())
    if unit is not None:
        raise SourceError(
            f"target CRS {value!r} has x/y in {unit[0]} ({unit[1]:.7g} m) while heights are "
            "metres; choose a projected CRS in metres, or 'auto'"
        )
    return crs.to_wkt()


def parse_resampling(value: str) -> str:
    """Validate a resampling name (one of :data:`RESAMPLINGS`)."""
    name = str(value).strip().lower()
    if name not in RESAMPLINGS:
        raise SourceError(f"resampling {value!r} is not one of {', '.join(RESAMPLINGS)}")
    return name


def utm_epsg(lon: float, lat: float) -> int:
    """EPSG code of the WGS 84 UTM zone containing ``(lon, lat)`` (326zz north, 327zz south)."""
    if not (math.isfinite(lon) and math.isfinite(lat) and -90 <= lat <= 90):
        raise SourceError(f"({lon}, {lat}) is not a longitude/latitude in degrees")
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = min(60, int((lon + 180.0) // 6.0) + 1)
    return (32600 if lat >= 0 else 32700) + zone


def _zone_bounds(epsg: int) -> tuple[float, float]:
    zone = epsg % 100
    west = -180.0 + 6.0 * (zone - 1)
    return west, west + 6.0


def auto_crs(bounds_lonlat: tuple[float, float, float, float]) -> CRS:
    """A metric CRS suited to an extent given as ``(west, south, east, north)`` degrees.

    The UTM zone of the centre when every longitude lies within that zone ± ``UTM_MARGIN_DEG``
    and the latitudes within UTM's 80°S..84°N; otherwise an azimuthal equidistant projection
    centred on the extent (distances from the centre exact, scale error < 1 % within ~1600 km).
    """
    west, south, east, north = (float(v) for v in bounds_lonlat)
    south, north = max(south, -90.0), min(north, 90.0)  # grid edges half a cell past a pole
    if east < west:  # crosses the antimeridian
        east += 360.0
    lon = (west + east) / 2.0
    lat = (south + north) / 2.0
    epsg = utm_epsg(lon, lat)
    zw, ze = _zone_bounds(epsg)
    zone_lon = (lon + 180.0) % 360.0 - 180.0
    shift = lon - zone_lon  # keep the zone bounds in the extent's longitude frame
    fits = (
        west >= zw + shift - UTM_MARGIN_DEG
        and east <= ze + shift + UTM_MARGIN_DEG
        and south >= UTM_LAT_RANGE[0]
        and north <= UTM_LAT_RANGE[1]
    )
    if fits:
        return CRS.from_epsg(epsg)
    lon = (lon + 180.0) % 360.0 - 180.0
    proj = f"+proj=aeqd +lat_0={lat:.6f} +lon_0={lon:.6f} +x_0=0 +y_0=0 +datum=WGS84 +units=m"
    reach, stretch = aeqd_stretch((west, south, east, north), lat, lon)
    where = (
        f"the DEM reaches {reach / 1000:,.0f} km from its centre ({lat:.4g}°, {lon:.4g}°), where "
        "the azimuthal equidistant projection chosen for it stretches "
        + (
            "distances without bound (the DEM holds the centre's antipode)"
            if math.isinf(stretch)
            else f"distances across the radius by {100 * (stretch - 1):.1f} %"
        )
    )
    if stretch > AUTO_STRETCH_MAX:
        raise SourceError(
            "{dst_crs_auto}: {where}: a flat terrain store holds a region, not a globe or a "
            "continent; tile it in pieces (`gdalwarp -te` on parts within ~4,800 km of their "
            "centres), or name a projection with {dst_crs} (this one, accepting the stretch: "
            "'{proj}')",
            params={"dst_crs_auto": "dst_crs='auto'", "dst_crs": "dst_crs"},
            where=where, proj=proj,
        )  # fmt: skip
    if stretch > AUTO_STRETCH_WARN:
        log.warning("auto CRS: %s; tile smaller parts for less", where)
    return CRS.from_proj4(proj + " +no_defs")


def aeqd_stretch(
    bounds_lonlat: tuple[float, float, float, float], lat0: float, lon0: float
) -> tuple[float, float]:
    """``(farthest distance m, largest scale factor)`` of the azimuthal equidistant projection
    centred at ``(lat0, lon0)`` over a ``(west, south, east, north)`` degree box, on the mean
    sphere: its scale across the radius is ``c / sin c`` at angular distance ``c`` (``inf``
    when the box holds the antipode, ``c = π``)."""
    west, south, east, north = bounds_lonlat
    anti_lat, anti_lon = -lat0, lon0 + 180.0
    in_lon = east - west >= 360.0 or (anti_lon - west) % 360.0 <= east - west
    if south <= anti_lat <= north and in_lon:
        return math.pi * EARTH_RADIUS_M, math.inf
    t = np.linspace(0.0, 1.0, 257)
    lons = np.concatenate([west + t * (east - west), np.full_like(t, east),
                           west + t * (east - west), np.full_like(t, west)])  # fmt: skip
    lats = np.concatenate([np.full_like(t, south), south + t * (north - south),
                           np.full_like(t, north), south + t * (north - south)])  # fmt: skip
    p0, l0 = math.radians(lat0), math.radians(lon0)
    p, lam = np.radians(lats), np.radians(lons)
    h = np.sin((p - p0) / 2) ** 2 + math.cos(p0) * np.cos(p) * np.sin((lam - l0) / 2) ** 2
    c = float((2 * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))).max())  # the farthest: on the edge
    return c * EARTH_RADIUS_M, (c / math.sin(c) if c > 1e-12 else 1.0)


def choose_crs(dst_crs: str, src_crs: CRS | None, bounds: tuple[float, ...]) -> CRS:
    """The target CRS for ``dst_crs`` (``"auto"`` or WKT from :func:`parse_dst_crs`).

    ``bounds`` are the sources' ``(left, bottom, right, top)`` in ``src_crs``.
    """
    return choose_crs_many(dst_crs, [(src_crs, bounds)])


def choose_crs_many(
    dst_crs: str,
    sources: Sequence[tuple[CRS | None, tuple[float, ...]]],
    names: Sequence[str] | None = None,
) -> CRS:
    """The target CRS for ``dst_crs`` (``"auto"`` or WKT) and sources given as ``(crs,
    (left, bottom, right, top))`` each in its own CRS: every one is checked to reach the target
    (or longitude/latitude, which ``auto`` needs), and ``auto`` fits the union of their
    longitude/latitude extents, taken the short way round (across the antimeridian when that is
    narrower). A refusal names the source (``names[i]``) when ``names`` are given."""
    target = None if dst_crs == AUTO else CRS.from_wkt(dst_crs)
    lonlat = []
    for i, (src_crs, b) in enumerate(sources):
        try:
            lonlat.append(_source_lonlat(src_crs, tuple(b), target))
        except SourceError as exc:
            if names is None:
                raise
            if exc.template is None:
                raise SourceError(f"{names[i]!r}: {exc}") from exc
            raise SourceError(
                "{source_name!r}: " + exc.template,
                params=exc.params,
                source_name=names[i],
                **exc.values,
            ) from exc
    return target if target is not None else auto_crs(lonlat_union(lonlat))


def _source_lonlat(
    src_crs: CRS | None, bounds: tuple[float, ...], target: CRS | None
) -> tuple[float, float, float, float]:
    """Refuse a source CRS that cannot be reprojected to ``target`` (None: to longitude/
    latitude, for ``auto``); its ``bounds`` in longitude/latitude when ``target`` is None."""
    if src_crs is None:
        raise SourceError(
            "the source has no CRS, so it cannot be reprojected; tile it without a target CRS"
        )
    if is_local(src_crs):
        raise SourceError(
            "the source's CRS is a local engineering one ({name!r}: x/y on no datum), so it "
            "cannot be placed on the Earth or reprojected; tile it without {dst_crs}",
            params={"dst_crs": "dst_crs"},
            name=src_crs.to_wkt().split('"')[1] if '"' in src_crs.to_wkt() else "unnamed",
        )
    left, bottom, right, top = bounds
    try:  # (within an Env: GDAL's "ERROR 1: PROJ ..." to logging, not to stderr)
        with rasterio.Env():
            # the centre first: a CRS of another body (Mars) has no operation to the target
            transform(src_crs, target or "EPSG:4326", [(left + right) / 2], [(bottom + top) / 2])
            if target is None and not src_crs.is_geographic:
                bounds = transform_bounds(src_crs, "EPSG:4326", *bounds)
    except Exception as exc:  # (GDAL/PROJ: no operation between the two)
        raise SourceError(
            "the source's CRS ({name}) has no transformation to {to} ({exc}): name a target "
            "CRS it can reach with {dst_crs}, or tile without one",
            params={"dst_crs": "dst_crs"},
            name=crs_name(src_crs.to_wkt()),
            to="longitude/latitude, which 'auto' needs"
            if target is None
            else crs_name(target.to_wkt()),
            exc=str(exc).split("\n")[0][:200],
        ) from exc
    w, s, e, n = (float(v) for v in bounds)
    return w, s, e, n


def lonlat_union(
    boxes: Sequence[tuple[float, float, float, float]],
) -> tuple[float, float, float, float]:
    """The smallest ``(west, south, east, north)`` holding every box, longitudes taken round the
    globe: boxes on both sides of the antimeridian (179..180 and -180..-179) make 179..181, not
    -180..180. ``east`` may exceed 180; a box with ``east < west`` crosses the antimeridian."""
    south = min(b[1] for b in boxes)
    north = max(b[3] for b in boxes)
    ivs = []  # each box's longitudes as intervals of [0, 360) (one crossing 360 cut in two)
    for w, _, e, _ in boxes:
        span = e - w if e >= w else e + 360.0 - w
        if span >= 360.0:
            return -180.0, south, 180.0, north
        start = w % 360.0
        if start + span > 360.0:
            ivs += [(start, 360.0), (0.0, start + span - 360.0)]
        else:
            ivs.append((start, start + span))
    ivs.sort()
    merged = [list(ivs[0])]
    for s0, e0 in ivs[1:]:
        if s0 <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], e0)
        else:
            merged.append([s0, e0])
    # the widest gap between the merged intervals (walking east) is what the union leaves out
    gap, gap_end = 0.0, merged[0][0]
    for (_, a_end), (b_start, _) in zip(merged, merged[1:], strict=False):
        if b_start - a_end > gap:
            gap, gap_end = b_start - a_end, b_start
    wrap = merged[0][0] + 360.0 - merged[-1][1]  # from the last interval round to the first
    if wrap >= gap:
        gap, gap_end = wrap, merged[0][0]
    if gap <= 0.0:
        return -180.0, south, 180.0, north
    west = (gap_end + 180.0) % 360.0 - 180.0
    return west, south, west + 360.0 - gap, north


def is_local(crs: CRS | None) -> bool:
    """True for a local engineering CRS (WKT ``LOCAL_CS`` / ``ENGCRS``: x/y on no datum)."""
    if crs is None:
        return False
    wkt = crs.to_wkt().lstrip().upper()
    return wkt.startswith(("LOCAL_CS", "ENGCRS", "ENGINEERINGCRS"))


def crs_name(wkt: str | None) -> str:
    """A short name for a CRS: ``EPSG:n`` when it has one, else its PROJ string or name."""
    if not wkt:
        return "none"
    crs = CRS.from_wkt(wkt)
    epsg = crs.to_epsg()
    if epsg:
        return f"EPSG:{epsg}"
    try:
        return crs.to_proj4() or crs.to_string()
    except CRSError:
        return crs.to_string()


def is_geographic(crs_wkt: str | None) -> bool:
    """True when the CRS's x/y are angles (degrees)."""
    return bool(crs_wkt) and CRS.from_wkt(crs_wkt).is_geographic


def horizontal_unit(crs_wkt: str | None) -> tuple[str, float] | None:
    """``(name, metres per unit)`` of a projected CRS's x/y; None without a CRS or for a
    geographic one."""
    if not crs_wkt:
        return None
    crs = CRS.from_wkt(crs_wkt)
    if crs.is_geographic:
        return None
    try:
        name, factor = crs.linear_units_factor
    except CRSError:  # not projected: an engineering (local) CRS has its axes' unit all the same
        try:
            name, factor = crs.units_factor
        except CRSError:
            return None
    return str(name), float(factor)


_VERT = re.compile(
    r'(?:VERT_CS|VERTCRS|VERTICALCRS)\[.*?(?:LENGTHUNIT|UNIT)\["([^"]+)",\s*([0-9.eE+-]+)'
)


def vertical_crs_unit(crs: Any) -> str | None:
    """The unit of a compound CRS's vertical part (``"foot"``, ``"US survey foot"``), as the
    vertical-unit names :mod:`tiler.vertical` knows; None without one or in metres."""
    if crs is None:
        return None
    m = _VERT.search(crs.to_wkt() if hasattr(crs, "to_wkt") else str(crs))
    if m is None:
        return None
    name, factor = m.group(1), float(m.group(2))
    if abs(factor - 1.0) < 1e-12:
        return None
    if abs(factor - 0.3048) < 1e-12:
        return "foot"
    if abs(factor - 1200.0 / 3937.0) < 1e-12:
        return "US survey foot"
    return name


def non_metre_unit(crs_wkt: str | None) -> tuple[str, float] | None:
    """:func:`horizontal_unit` when it is not the metre (e.g. US survey feet), else None."""
    unit = horizontal_unit(crs_wkt)
    return unit if unit is not None and abs(unit[1] - 1.0) > 1e-9 else None


def require_projected(meta_or_store: Any) -> None:
    """Raise ``GeographicStoreError`` if a store (or its ``StoreMeta``) is in a geographic CRS
    or one whose x/y are not metres, ``StoreHeightsError`` if it holds values beyond ±1000 km.

    Streaming, rendering and every measurement need x/y in the same unit as heights.
    """
    meta = getattr(meta_or_store, "meta", meta_or_store)
    wkt = getattr(meta, "crs_wkt", None)
    url = getattr(meta_or_store, "url", None)
    where = f"store {url!r}" if url else "this store"
    src = (getattr(meta, "source", None) or {}).get("path") or "SRC"
    require_heights(meta, where, str(src))
    unit = non_metre_unit(wkt)
    if unit is not None:
        raise GeographicStoreError(
            "{where} is in {crs}, whose x/y are in {unit} ({factor:.7g} m) while heights are "
            "metres: drawn, it would be stretched {stretch:.3g}x across, so it cannot be "
            "streamed or rendered. Tile the source again with a target CRS in metres: "
            "{retile}.",
            params={"retile": "tile({src!r}, dst, TileOptions(dst_crs='auto'))"},
            where=where,
            crs=crs_name(wkt),
            unit=unit[0],
            factor=unit[1],
            stretch=1.0 / unit[1],
            src=str(src),
        )
    if not is_geographic(wkt):
        return
    raise GeographicStoreError(
        "{where} is in a geographic CRS ({crs}): its x/y are degrees while heights are metres, "
        "so it cannot be streamed or rendered. Tile the source again with a projected target "
        "CRS: {retile}.",
        params={"retile": "tile({src!r}, dst, TileOptions(dst_crs='auto'))"},
        where=where,
        crs=crs_name(wkt),
        src=str(src),
    )
