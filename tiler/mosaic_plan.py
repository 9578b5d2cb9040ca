"""Planning a mosaic (:func:`plan_mosaic`): every source's header read once and laid out on
one target grid, aligned (same CRS, pixel size and grid) or reprojected (each source's
footprint from its warped sample-centre hull), as a picklable :class:`MosaicSpec` that
:class:`tiler.mosaic.MosaicReader` reads from (see :mod:`tiler.mosaic` for the overlap rule).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from rasterio.crs import CRS
from rasterio.transform import Affine
from rasterio.warp import transform as warp_transform
from rasterio.warp import transform_bounds

from tiler.crs import (
    choose_crs_many,
    crs_name,
    lonlat_union,
    parse_dst_crs,
    parse_resampling,
)
from tiler.encoding import parse_dtype
from tiler.errors import SourceError
from tiler.source_header import SourceInfo, read_info
from tiler.vertical import metres_per_unit

log = logging.getLogger(__name__)

ALIGN_TOL = 1e-3  # pixels: how far a source's origin may sit off the mosaic's pixel grid


@dataclass(frozen=True)
class MosaicSpec:
    """Picklable description of a mosaic on its target grid (what a worker re-opens)."""

    sources: tuple[SourceInfo, ...]
    band: int
    width: int
    height: int
    transform: tuple[float, float, float, float, float, float]
    crs_wkt: str | None
    dtype: str
    nodata: float | None
    source_crs_wkt: str | None
    warp: bool = False
    resampling: str = "bilinear"
    dst_crs: str | None = None  # as requested ("auto" or WKT)

    @property
    def affine(self) -> Affine:
        """The target grid's transform (pixel corners)."""
        return Affine(*self.transform)

    @property
    def label(self) -> str:
        """The sources for a message: the first one's path and how many more."""
        first = self.sources[0].path if self.sources else "(no source)"
        more = len(self.sources) - 1
        return first + (f" and {more} more source(s)" if more > 0 else "")


def _same(values: list, what: str, infos: Sequence[SourceInfo]) -> object:
    first = values[0]
    for v, info in zip(values, infos, strict=True):
        if v != first:
            raise SourceError(
                f"sources disagree on {what}: {infos[0].path!r} has {first!r}, "
                f"{info.path!r} has {v!r}; a mosaic needs one {what}"
            )
    return first


def _mosaic_nodata(infos: Sequence[SourceInfo], dtype: np.dtype, covered: bool) -> float | None:
    """The first source's nodata; if none has one: None when the sources cover the whole
    grid and none has a mask, else NaN (floats) or the dtype's minimum (integers) for the gaps
    and the masked samples."""
    for info in infos:
        if info.nodata is not None:
            return info.nodata
    if covered and not any(i.masked for i in infos):
        return None
    return float("nan") if dtype.kind == "f" else float(np.iinfo(dtype).min)


def _covers(rects: Sequence[tuple[int, int, int, int]], height: int, width: int) -> bool:
    """True when the union of ``(r0, c0, r1, c1)`` rectangles covers ``height x width``."""
    rows = sorted({0, height, *(r[0] for r in rects), *(r[2] for r in rects)})
    cols = sorted({0, width, *(r[1] for r in rects), *(r[3] for r in rects)})
    ri = {v: i for i, v in enumerate(rows)}
    ci = {v: i for i, v in enumerate(cols)}
    cover = np.zeros((len(rows) - 1, len(cols) - 1), dtype=bool)
    for r0, c0, r1, c1 in rects:
        cover[ri[r0] : ri[r1], ci[c0] : ci[c1]] = True
    return bool(cover.all())


def plan_mosaic(
    paths: Sequence[str | os.PathLike],
    band: int = 1,
    dst_crs: str | None = None,
    resolution: float | tuple[float, float] | None = None,
    resampling: str = "bilinear",
) -> MosaicSpec:
    """Read every source's header and lay them out on one target grid (see module doc)."""
    paths = [str(p) for p in paths]
    if not paths:
        raise SourceError("no source rasters given")
    infos = [read_info(p, band) for p in paths]
    dtype = parse_dtype(np.result_type(*[np.dtype(i.dtype) for i in infos]))
    _same(
        [(i.scale, i.offset, metres_per_unit(i.units)) for i in infos],
        "height scale, offset and metres per vertical unit",
        infos,
    )
    crss = [CRS.from_wkt(i.crs_wkt) if i.crs_wkt else None for i in infos]
    if dst_crs is None and resolution is not None:
        raise SourceError("a resolution applies when reprojecting; give a target CRS too")
    if dst_crs is not None:  # each source is warped from its own CRS
        return _plan_warped(
            infos, band, dtype, crss, parse_dst_crs(dst_crs), resolution, resampling
        )
    for c, info in zip(crss, infos, strict=True):
        if c != crss[0]:
            raise SourceError(
                "sources are in different CRSs ({first!r}: {a}, {path!r}: {b}); give a target "
                "CRS with {dst_crs} (e.g. 'auto') to reproject them onto one grid",
                params={"dst_crs": "dst_crs"},
                first=infos[0].path, a=crs_name(crss[0].to_wkt()) if crss[0] else "none",
                path=info.path, b=crs_name(c.to_wkt()) if c else "none",
            )  # fmt: skip
    return _plan_aligned(infos, band, dtype, crss[0])


def _plan_aligned(
    infos: list[SourceInfo], band: int, dtype: np.dtype, src_crs: CRS | None
) -> MosaicSpec:
    for info in infos:
        a, b, _, d, e, _ = info.transform
        if abs(b) > 1e-12 * abs(a) or abs(d) > 1e-12 * abs(e) or e == 0:
            raise SourceError(
                f"{info.path!r} has a rotated geotransform {info.transform}; give a target CRS "
                "to reproject it north-up while tiling"
            )
    # a south-up source (rows from south to north), or one whose columns run from east to
    # west, is placed, and read, flipped: no resampling
    north = [_north_up(info) for info in infos]
    a, _, c, _, e, f = north[0]
    for info, nt in zip(infos, north, strict=True):
        ia, ie = nt[0], nt[4]
        if abs(ia - a) > 1e-9 * abs(a) or abs(ie - e) > 1e-9 * abs(e):
            raise SourceError(
                f"sources have different pixel sizes ({infos[0].path!r}: {a:g} x {-e:g}, "
                f"{info.path!r}: {ia:g} x {-ie:g}); give a target CRS and resolution to "
                "resample them onto one grid"
            )
    offsets = []
    for info, nt in zip(infos, north, strict=True):
        col = (nt[2] - c) / a
        row = (nt[5] - f) / e
        if abs(col - round(col)) > ALIGN_TOL or abs(row - round(row)) > ALIGN_TOL:
            raise SourceError(
                f"{info.path!r} is not on the pixel grid of {infos[0].path!r} (offset of "
                f"{col:.4f}, {row:.4f} pixels); give a target CRS to resample them onto one grid"
            )
        offsets.append((round(row), round(col)))
    r_min = min(r for r, _ in offsets)
    c_min = min(c_ for _, c_ in offsets)
    placed = tuple(
        _with_footprint(i, r - r_min, c_ - c_min, r - r_min + i.height, c_ - c_min + i.width)
        for i, (r, c_) in zip(infos, offsets, strict=True)
    )
    height = max(p.footprint[2] for p in placed)
    width = max(p.footprint[3] for p in placed)
    t = Affine(a, 0.0, c + c_min * a, 0.0, e, f + r_min * e)
    if src_crs is not None and src_crs.is_geographic and len(placed) > 1:
        _warn_antimeridian(placed, width * abs(a))
    return MosaicSpec(
        sources=placed,
        band=band,
        width=width,
        height=height,
        transform=tuple(t)[:6],
        crs_wkt=src_crs.to_wkt() if src_crs else None,
        dtype=dtype.name,
        nodata=_mosaic_nodata(infos, dtype, _covers([p.footprint for p in placed], height, width)),
        source_crs_wkt=src_crs.to_wkt() if src_crs else None,
    )


def _warn_antimeridian(placed: Sequence[SourceInfo], span_deg: float) -> None:
    """Warn when geographic sources lie on both sides of the antimeridian: their grid in
    degrees runs the long way round (a mostly empty grid of ``span_deg``), where a target CRS
    makes one small grid of their short-way union."""
    boxes = [_bounds(p) for p in placed]
    west, _, east, _ = lonlat_union(boxes)
    if span_deg > 180.0 and east - west < span_deg / 2:
        log.warning(
            "the sources lie on both sides of the antimeridian: in degrees their grid runs the "
            "long way round (%.1f° of longitude, mostly empty, where they cover %.1f°); "
            "`--dst-crs auto` makes one grid of what they cover",
            span_deg,
            east - west,
        )


def _north_up(info: SourceInfo) -> tuple[float, float, float, float, float, float]:
    """The source's geotransform with its rows counted from the north and its columns from
    the west (as it is if they are)."""
    a, b, c, d, e, f = info.transform
    if e > 0:  # row 0 is the southern edge: the north-up grid starts at the last row's end
        e, f = -e, f + e * info.height
    if a < 0:  # column 0 is the eastern edge: the grid starts at the last column's end
        a, c = -a, c + a * info.width
    return (a, b, c, d, e, f)


def _with_footprint(info: SourceInfo, r0: int, c0: int, r1: int, c1: int) -> SourceInfo:
    return replace(info, footprint=(r0, c0, r1, c1))


#: how many times finer than the source's pixel a target ``resolution`` may be (per axis):
#: finer is a unit mistake (degrees given as metres), not an upsampling anyone wants
MAX_UPSAMPLE = 100.0
HULL_POINTS = 64  # points per edge of a source's sample-centre hull
SEAM_POINTS = 16  # points per edge of the seam rings (chords ~1 m off over a 1° tile)
HULL_EPS = 1e-3  # source pixels the hull is widened by, so samples on it are kept (no ties)


def _hull(
    info: SourceInfo,
    src_crs: CRS,
    target: CRS,
    widen: float = HULL_EPS,
    widen_cols: float | None = None,
    points: int = HULL_POINTS,
) -> tuple[tuple[float, float], ...]:
    """The ring through the source's outer sample centres, in target coordinates (``widen``
    source pixels out across its rows, ``widen_cols`` across its columns, default the same:
    0.5 is the ring of its pixel edges).

    Reprojected samples outside it would be extrapolated (GDAL holds edge values constant
    there), so they are left out: the store ends where the source's samples end.
    """
    t = Affine(*info.transform)
    n = points
    e, f = widen, widen if widen_cols is None else widen_cols
    r0, c0, r1, c1 = -e, -f, info.height - 1 + e, info.width - 1 + f
    edge = np.linspace(0.0, 1.0, n, endpoint=False)
    rows = np.concatenate(
        [r0 + 0 * edge, r0 + edge * (r1 - r0), r1 + 0 * edge, r1 - edge * (r1 - r0)]
    )
    cols = np.concatenate(
        [c0 + edge * (c1 - c0), c1 + 0 * edge, c1 - edge * (c1 - c0), c0 + 0 * edge]
    )
    xs, ys = t * (cols + 0.5, rows + 0.5)
    if src_crs.is_geographic:  # a sample centre on a pole, widened past it
        ys = np.clip(ys, -90.0, 90.0)
    tx, ty = warp_transform(src_crs, target, xs.tolist(), ys.tolist())
    ring = list(zip(tx, ty, strict=True))
    return tuple((*ring, ring[0]))


def _bounds(info: SourceInfo) -> tuple[float, float, float, float]:
    """``(left, bottom, right, top)`` of a source's pixel corners (any affine transform)."""
    t = Affine(*info.transform)
    xs, ys = zip(
        *(t * p for p in ((0, 0), (info.width, 0), (0, info.height), (info.width, info.height))),
        strict=True,
    )
    return min(xs), min(ys), max(xs), max(ys)


def _on_earth(bounds: tuple[float, ...], crs: CRS | None) -> tuple[float, float, float, float]:
    """``bounds`` with latitudes clamped to the poles when ``crs`` is geographic (the pixel
    edges of a grid whose first row is centred on a pole lie half a pixel past it)."""
    left, bottom, right, top = bounds
    if crs is not None and crs.is_geographic:
        bottom, top = max(bottom, -90.0), min(top, 90.0)
    return left, bottom, right, top


def _extent_in(
    crs: CRS, own: Sequence[tuple[float, float, float, float]], crss: Sequence[CRS | None]
) -> tuple[float, float, float, float]:
    """The union of the extents of the sources in ``crs`` (longitudes the short way round the
    globe when it is geographic: tiles on both sides of the antimeridian make 179..181)."""
    same = np.array([b for b, c in zip(own, crss, strict=True) if c == crs])
    left, bottom = float(same[:, 0].min()), float(same[:, 1].min())
    right, top = float(same[:, 2].max()), float(same[:, 3].max())
    if crs.is_geographic:
        wrapped = lonlat_union([tuple(b) for b in same])
        if wrapped[2] - wrapped[0] < right - left - 1e-9:  # shorter across the antimeridian
            return wrapped
    return left, bottom, right, top


def _finest_pixel(info: SourceInfo, bounds: tuple[float, ...], src_crs: CRS, target: CRS) -> float:
    """The source's finer pixel side, in target units, at the centre of ``bounds``: the
    default resolution (the finest over the sources), so reprojection loses no detail along
    either axis."""
    a, b, _, d, e, _ = info.transform
    cx, cy = (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2
    xs, ys = warp_transform(src_crs, target, [cx, cx + a, cx + b], [cy, cy + d, cy + e])
    dx = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
    dy = math.hypot(xs[2] - xs[0], ys[2] - ys[0])
    return min(dx, dy)


#: the largest shift (degrees, ~1 m) a source's CRS may lose by being wrapped at ±180°
WRAP_TOLERANCE_DEG = 1e-5


def wrapped_crs(info: SourceInfo) -> CRS | None:
    """For a geographic source whose longitudes run past ±180 (179..181, or 0..360), its CRS
    with longitudes wrapped round its centre (PROJ's ``+lon_wrap``), else None (its own).

    GDAL's warper maps each target pixel back to -180..180, so the part of such a source past
    the antimeridian (181 read as -179) was found in no sample and silently became nodata.
    """
    if not info.crs_wkt:
        return None
    crs = CRS.from_wkt(info.crs_wkt)
    if not crs.is_geographic:
        return None
    t = Affine(*info.transform)
    xs = [(t * (c, r))[0] for c in (0, info.width) for r in (0, info.height)]
    if min(xs) >= -180.0 and max(xs) <= 180.0:
        return None
    centre = (min(xs) + max(xs)) / 2.0
    wrapped = CRS.from_proj4(f"{crs.to_proj4()} +lon_wrap={centre:.9g}")
    # a PROJ string keeps no datum transformation PROJ would pick from the CRS itself (NAD27:
    # 265 m at 179.5°E): checked on a point inside -180..180, refused past ~1 m
    ys = [(t * (0, r))[1] for r in (0, info.height)]
    lons, lats = (  # a 9 x 5 lattice over the source: the shift varies (and grids end)
        v.ravel() for v in np.meshgrid(np.linspace(min(xs), max(xs), 9), np.linspace(*ys, 5))
    )
    lats = np.clip(lats, -90.0, 90.0)
    ax, ay = warp_transform(
        crs, "EPSG:4326", ((lons + 180.0) % 360.0 - 180.0).tolist(), lats.tolist()
    )
    bx, by = warp_transform(wrapped, "EPSG:4326", lons.tolist(), lats.tolist())
    dx = (np.asarray(ax) - np.asarray(bx) + 180.0) % 360.0 - 180.0
    off = float(max(np.abs(dx).max(), np.abs(np.asarray(ay) - np.asarray(by)).max()))
    if off > WRAP_TOLERANCE_DEG:
        raise SourceError(
            f"{info.path!r} runs past ±180° of longitude in {crs.to_string()!r}, whose datum "
            "shift cannot be kept while its longitudes are wrapped (it would be placed up to "
            f"{off * 111_000:.0f} m off); warp it to EPSG:4326 first "
            "(`gdalwarp -t_srs EPSG:4326 SRC out.tif`) and tile that"
        )
    return wrapped


def _plan_warped(
    infos: list[SourceInfo],
    band: int,
    dtype: np.dtype,
    crss: list[CRS | None],
    dst_crs: str,
    resolution: float | tuple[float, float] | None,
    resampling: str,
) -> MosaicSpec:
    resampling = parse_resampling(resampling)
    for i in infos:  # (refused now, not by a worker once the store is begun)
        wrapped_crs(i)
    # every source's extent in its own CRS: the target grid is the union of their extents
    # on the target (a union taken in one source CRS would span the globe for tiles on both
    # sides of the antimeridian)
    own = [_on_earth(_bounds(i), c) for i, c in zip(infos, crss, strict=True)]
    names = [i.path for i in infos] if len(infos) > 1 else None
    target = choose_crs_many(dst_crs, list(zip(crss, own, strict=True)), names)
    if resolution is not None:
        res = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
        if not all(math.isfinite(r) and r > 0 for r in res):
            raise SourceError(f"resolution must be positive target CRS units, got {resolution}")
    # the finest source's pixel (as gdalwarp): a finer source listed after a coarser one keeps
    # its detail (sources of one CRS and pixel size are measured once, at their extent's centre)
    kinds: dict[tuple, tuple[SourceInfo, CRS]] = {}
    for i, c in zip(infos, crss, strict=True):
        kinds.setdefault(
            (c.to_wkt(), *(abs(v) for v in i.transform[:2] + i.transform[3:5])), (i, c)
        )
    native = min(_finest_pixel(i, _extent_in(c, own, crss), c, target) for i, c in kinds.values())
    if resolution is None:
        r = float(f"{native:.3g}")
        res = (r, r)
    elif min(res) < native / MAX_UPSAMPLE:
        raise SourceError(
            "{resolution} {res:g} is {factor:,.0f}x finer than the source's pixels (~{native:.4g}"
            " m in the target CRS): it is in the target CRS's metres, not the source's units; "
            "give at least {least:.3g} (or none: the source's own)",
            params={"resolution": "resolution"},
            res=min(res), factor=native / min(res), native=native, least=native / MAX_UPSAMPLE,
        )  # fmt: skip
    boxes = [
        transform_bounds(c, target, *b, densify_pts=51) for c, b in zip(crss, own, strict=True)
    ]
    if all(c == crss[0] for c in crss):  # (one CRS: their union's extent, as before)
        union = _extent_in(crss[0], own, crss)
        left, bottom, right, top = transform_bounds(crss[0], target, *union, densify_pts=51)
    else:
        left, bottom = min(b[0] for b in boxes), min(b[1] for b in boxes)
        right, top = max(b[2] for b in boxes), max(b[3] for b in boxes)
    ew, ns = right - left, top - bottom
    # snap to multiples of the resolution (gdalwarp -tap), so separate runs share one grid
    left = math.floor(left / res[0]) * res[0]
    right = math.ceil(right / res[0]) * res[0]
    bottom = math.floor(bottom / res[1]) * res[1]
    top = math.ceil(top / res[1]) * res[1]
    width = round((right - left) / res[0])
    height = round((top - bottom) / res[1])
    if resolution is not None and min(width, height) < 2:
        raise SourceError(
            "{resolution} {res:g} leaves a {w}x{h} grid across the sources' {ew:,.0f} x "
            "{ns:,.0f} m: a DEM needs at least 2x2 samples; give at most {most:.3g}",
            params={"resolution": "resolution"},
            res=max(res), w=width, h=height, ew=ew, ns=ns, most=min(ew, ns) / 2,
        )  # fmt: skip
    t = Affine(res[0], 0.0, left, 0.0, -res[1], top)
    placed = []
    for i, c, sb in zip(infos, crss, boxes, strict=True):
        c0 = max(0, math.floor((sb[0] - left) / res[0]) - 2)
        c1 = min(width, math.ceil((sb[2] - left) / res[0]) + 2)
        r0 = max(0, math.floor((top - sb[3]) / res[1]) - 2)
        r1 = min(height, math.ceil((top - sb[1]) / res[1]) + 2)
        placed.append(replace(_with_footprint(i, r0, c0, r1, c1), hull=_hull(i, c, target)))
    placed = _with_seams(placed, crss, target)
    return MosaicSpec(
        sources=tuple(placed),
        band=band,
        width=width,
        height=height,
        transform=tuple(t)[:6],
        crs_wkt=target.to_wkt(),
        dtype=dtype.name,
        nodata=_mosaic_nodata(infos, dtype, covered=False),
        source_crs_wkt=crss[0].to_wkt() if crss[0] else None,
        warp=True,
        resampling=resampling,
        dst_crs=dst_crs,
    )


def _with_seams(placed: list[SourceInfo], crss: Sequence[CRS], target: CRS) -> list[SourceInfo]:
    """Each source with the indices of the others whose footprint meets it (none: no seam):
    :class:`~tiler.mosaic.MosaicReader` fills their seams from :func:`seam_rings`, which it
    builds itself (a spec holding the rings was ~5x larger, and is shipped with every block
    task of a dask run)."""
    fp = np.array([p.footprint for p in placed], dtype=np.int64).reshape(-1, 4)
    out = []
    for k, p in enumerate(placed):
        meet = (fp[:, 0] < fp[k, 2]) & (fp[:, 2] > fp[k, 0]) & (fp[:, 1] < fp[k, 3])
        meet &= fp[:, 3] > fp[k, 1]
        meet[k] = False
        others = tuple(np.nonzero(meet)[0].tolist())
        out.append(replace(p, near=others) if others else p)
    return out


Ring = tuple[tuple[float, float], ...]


def seam_rings(info: SourceInfo, target: CRS) -> tuple[Ring, tuple[Ring, Ring, Ring]]:
    """The rings, in ``target`` coordinates, :class:`~tiler.mosaic.MosaicReader` fills seams
    from: the source's pixel edges, and three round its sample centres, one source pixel out
    across its columns only, across its rows only, and both."""
    src = CRS.from_wkt(info.crs_wkt)
    edge = _hull(info, src, target, widen=0.5, points=SEAM_POINTS)
    cols, rows, both = (
        _hull(info, src, target, widen=a, widen_cols=b, points=SEAM_POINTS)
        for a, b in ((HULL_EPS, 1.0), (1.0, HULL_EPS), (1.0, 1.0))
    )
    return edge, (cols, rows, both)
