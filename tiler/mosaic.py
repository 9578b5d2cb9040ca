"""Many rasters as one DEM, read window by window, optionally reprojected on the fly.

:func:`plan_mosaic` opens each source once for its header and returns a picklable
:class:`MosaicSpec` (the target grid and every source's footprint on it), so worker processes
can re-open it. :class:`MosaicReader` reads any window of the target grid: it picks the sources
whose footprint meets the window and reads only that part of each (through a ``WarpedVRT``
when reprojecting). No source is read whole and the mosaic never exists in memory or on disk;
a window costs at most its own size per overlapping source, whatever the number of files.

Overlap rule: **the first source in the given order that has a valid sample at a position
wins** (like ``rasterio.merge``'s ``first``); later sources only fill the earlier ones' nodata
and gaps. Without reprojection, sources must share CRS, pixel size and pixel grid, so adjacent
SRTM tiles that share their edge row are placed exactly on it. Positions no source covers are
nodata.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import rasterio
import rasterio.errors
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.features import geometry_mask
from rasterio.transform import Affine
from rasterio.vrt import WarpedVRT
from rasterio.warp import transform as warp_transform
from rasterio.warp import transform_bounds
from rasterio.windows import Window

from tiler.crs import choose_crs, parse_dst_crs, parse_resampling
from tiler.encoding import parse_dtype
from tiler.errors import SourceError, SourceReadError
from tiler.source_header import SourceInfo, _open, read_info  # noqa: F401  (re-exported)
from tiler.vertical import metres_per_unit

ALIGN_TOL = 1e-3  # pixels: how far a source's origin may sit off the mosaic's pixel grid
MAX_OPEN = 16  # datasets a reader keeps open (least recently used are closed)
WARP_TOLERANCE = 0.01  # source pixels of transform approximation (GDAL: 0.125); see notes


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
    for c, info in zip(crss, infos, strict=True):
        if c != crss[0]:
            raise SourceError(
                f"sources are in different CRSs ({infos[0].path!r}: {crss[0]}, {info.path!r}: "
                f"{c}); give a target CRS to reproject them onto one grid"
            )
    src_crs = crss[0]
    if dst_crs is None and resolution is not None:
        raise SourceError("a resolution applies when reprojecting; give a target CRS too")
    if dst_crs is None:
        return _plan_aligned(infos, band, dtype, src_crs)
    return _plan_warped(infos, band, dtype, src_crs, parse_dst_crs(dst_crs), resolution, resampling)


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
    # a south-up source (rows from south to north) is placed, and read, flipped: no resampling
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


def _north_up(info: SourceInfo) -> tuple[float, float, float, float, float, float]:
    """The source's geotransform with its rows counted from the north (as it is if they are)."""
    a, b, c, d, e, f = info.transform
    if e > 0:  # row 0 is the southern edge: the north-up grid starts at the last row's end
        return (a, b, c, d, -e, f + e * info.height)
    return info.transform


def _with_footprint(info: SourceInfo, r0: int, c0: int, r1: int, c1: int) -> SourceInfo:
    return replace(info, footprint=(r0, c0, r1, c1))


#: how many times finer than the source's pixel a target ``resolution`` may be (per axis):
#: finer is a unit mistake (degrees given as metres), not an upsampling anyone wants
MAX_UPSAMPLE = 100.0
HULL_POINTS = 64  # points per edge of a source's sample-centre hull
HULL_EPS = 1e-3  # source pixels the hull is widened by, so samples on it are kept (no ties)


def _hull(info: SourceInfo, src_crs: CRS, target: CRS) -> tuple[tuple[float, float], ...]:
    """The ring through the source's outer sample centres, in target coordinates.

    Reprojected samples outside it would be extrapolated (GDAL holds edge values constant
    there), so they are left out: the store ends where the source's samples end.
    """
    t = Affine(*info.transform)
    n = HULL_POINTS
    e = HULL_EPS
    r0, c0, r1, c1 = -e, -e, info.height - 1 + e, info.width - 1 + e
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


def _union_bounds(infos: Sequence[SourceInfo]) -> tuple[float, float, float, float]:
    b = np.array([_bounds(i) for i in infos])
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


def _finest_pixel(info: SourceInfo, bounds: tuple[float, ...], src_crs: CRS, target: CRS) -> float:
    """The source's finer pixel side, in target units, at the centre of the extent: the
    default resolution, so reprojection loses no detail along either axis."""
    a, b, _, d, e, _ = info.transform
    cx, cy = (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2
    xs, ys = warp_transform(src_crs, target, [cx, cx + a, cx + b], [cy, cy + d, cy + e])
    dx = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
    dy = math.hypot(xs[2] - xs[0], ys[2] - ys[0])
    return min(dx, dy)


def _plan_warped(
    infos: list[SourceInfo],
    band: int,
    dtype: np.dtype,
    src_crs: CRS | None,
    dst_crs: str,
    resolution: float | tuple[float, float] | None,
    resampling: str,
) -> MosaicSpec:
    resampling = parse_resampling(resampling)
    bounds = _on_earth(_union_bounds(infos), src_crs)
    target = choose_crs(dst_crs, src_crs, bounds)
    if resolution is not None:
        res = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
        if not all(math.isfinite(r) and r > 0 for r in res):
            raise SourceError(f"resolution must be positive target CRS units, got {resolution}")
    native = _finest_pixel(infos[0], bounds, src_crs, target)
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
    left, bottom, right, top = transform_bounds(src_crs, target, *bounds, densify_pts=51)
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
    for i in infos:
        sb = transform_bounds(src_crs, target, *_on_earth(_bounds(i), src_crs), densify_pts=51)
        c0 = max(0, math.floor((sb[0] - left) / res[0]) - 2)
        c1 = min(width, math.ceil((sb[2] - left) / res[0]) + 2)
        r0 = max(0, math.floor((top - sb[3]) / res[1]) - 2)
        r1 = min(height, math.ceil((top - sb[1]) / res[1]) + 2)
        placed.append(replace(_with_footprint(i, r0, c0, r1, c1), hull=_hull(i, src_crs, target)))
    return MosaicSpec(
        sources=tuple(placed),
        band=band,
        width=width,
        height=height,
        transform=tuple(t)[:6],
        crs_wkt=target.to_wkt(),
        dtype=dtype.name,
        nodata=_mosaic_nodata(infos, dtype, covered=False),
        source_crs_wkt=src_crs.to_wkt() if src_crs else None,
        warp=True,
        resampling=resampling,
        dst_crs=dst_crs,
    )


def _valid(data: np.ndarray, nodata: float | None) -> np.ndarray:
    valid = np.ones(data.shape, dtype=bool)
    if data.dtype.kind == "f":
        valid &= np.isfinite(data)
    if nodata is not None and not np.isnan(nodata):
        valid &= data != np.asarray(nodata).astype(data.dtype)
    return valid


def _read(fn: Callable[..., np.ndarray], band: int, win: Window, path: str) -> np.ndarray:
    """``fn(band, window=win)`` (a dataset's ``read`` or ``read_masks``), a GDAL read failure
    raised as :class:`SourceReadError` naming the file and the window."""
    try:
        return fn(band, window=win)
    except rasterio.errors.RasterioIOError as exc:
        cause: BaseException = exc
        while cause.__cause__ is not None:  # GDAL's first complaint says the most
            cause = cause.__cause__
        rows = f"{int(win.row_off)}..{int(win.row_off + win.height) - 1}"
        cols = f"{int(win.col_off)}..{int(win.col_off + win.width) - 1}"
        raise SourceReadError(
            f"reading {path!r} failed in rows {rows}, columns {cols} of its grid (GDAL says: "
            f"{cause}); the file may be truncated or damaged (`gdalinfo -checksum` reads all "
            "of it), or, for a URL, its server failed"
        ) from exc


class MosaicReader:
    """Reads windows of a :class:`MosaicSpec`'s target grid; one per thread or process."""

    def __init__(self, spec: MosaicSpec, max_open: int = MAX_OPEN) -> None:
        self.spec = spec
        self.max_open = max(1, int(max_open))
        self._open: OrderedDict[int, tuple[rasterio.DatasetReader, WarpedVRT | None]] = (
            OrderedDict()
        )
        fp = np.array([s.footprint for s in spec.sources], dtype=np.int64).reshape(-1, 4)
        self._fp = fp
        self.dtype = np.dtype(spec.dtype)
        self.height, self.width = spec.height, spec.width
        # the nodata value :func:`_mosaic_nodata` chose (no source declares one), if a sample
        # could take it (not NaN): a valid sample equal to it would read as nodata
        chosen = spec.nodata is not None and not np.isnan(spec.nodata)
        self._chosen = chosen and all(s.nodata is None for s in spec.sources)

    def __enter__(self) -> MosaicReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close every open source."""
        while self._open:
            _, (ds, vrt) = self._open.popitem()
            if vrt is not None:
                vrt.close()
            ds.close()

    def _dataset(self, i: int) -> rasterio.DatasetReader | WarpedVRT:
        if i in self._open:
            self._open.move_to_end(i)
            ds, vrt = self._open[i]
            return vrt or ds
        while len(self._open) >= self.max_open:
            _, (old, old_vrt) = self._open.popitem(last=False)
            if old_vrt is not None:
                old_vrt.close()
            old.close()
        spec = self.spec
        ds = _open(spec.sources[i].path)
        vrt = None
        if spec.warp:
            info = spec.sources[i]
            vrt = WarpedVRT(
                ds,
                crs=CRS.from_wkt(spec.crs_wkt),
                transform=spec.affine,
                width=spec.width,
                height=spec.height,
                resampling=Resampling[spec.resampling],
                src_nodata=info.nodata,
                nodata=spec.nodata,
                dtype=spec.dtype,
                tolerance=WARP_TOLERANCE,
            )
        self._open[i] = (ds, vrt)
        return vrt or ds

    def sources_for(self, r0: int, c0: int, h: int, w: int) -> list[int]:
        """Indices (in priority order) of the sources whose footprint meets the window."""
        fp = self._fp
        hit = (fp[:, 0] < r0 + h) & (fp[:, 2] > r0) & (fp[:, 1] < c0 + w) & (fp[:, 3] > c0)
        return np.nonzero(hit)[0].tolist()

    def read_window(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        """Samples of rows ``r0..r0+h`` and columns ``c0..c0+w`` of the target grid."""
        spec = self.spec
        hits = self.sources_for(r0, c0, h, w)
        if len(hits) == 1 and not spec.warp and not spec.sources[hits[0]].masked:
            fr0, fc0, fr1, fc1 = (int(v) for v in self._fp[hits[0]])
            if fr0 <= r0 and fc0 <= c0 and r0 + h <= fr1 and c0 + w <= fc1:  # inside one source
                data, _ = self._read_aligned(hits[0], r0 - fr0, c0 - fc0, h, w)
                self._check_chosen_nodata(data, None, hits[0])
                return data.astype(self.dtype, copy=False)
        fill = np.asarray(spec.nodata if spec.nodata is not None else 0).astype(self.dtype)
        out = np.full((h, w), fill, dtype=self.dtype)
        filled = np.zeros((h, w), dtype=bool)
        for i in hits:
            fr0, fc0, fr1, fc1 = (int(v) for v in self._fp[i])
            ir0, ir1 = max(r0, fr0), min(r0 + h, fr1)
            ic0, ic1 = max(c0, fc0), min(c0 + w, fc1)
            if spec.warp:  # (GDAL's warper applies the source's mask itself)
                win = Window(ic0, ir0, ic1 - ic0, ir1 - ir0)
                data = _read(self._dataset(i).read, spec.band, win, spec.sources[i].path)
                valid = _valid(data, spec.nodata)
            else:  # aligned: the footprint is the source's own pixel grid
                data, mask = self._read_aligned(i, ir0 - fr0, ic0 - fc0, ir1 - ir0, ic1 - ic0)
                valid = _valid(data, spec.sources[i].nodata)
                if mask is not None:
                    valid &= mask
            self._check_chosen_nodata(data, valid, i)
            if spec.warp and spec.sources[i].hull:
                valid &= geometry_mask(
                    [{"type": "Polygon", "coordinates": [spec.sources[i].hull]}],
                    out_shape=data.shape,
                    transform=spec.affine * Affine.translation(ic0, ir0),
                    invert=True,
                )
            sub = (slice(ir0 - r0, ir1 - r0), slice(ic0 - c0, ic1 - c0))
            take = valid & ~filled[sub]
            out[sub][take] = data[take].astype(self.dtype)
            filled[sub] |= take
            if filled.all():
                break
        return out

    def _read_aligned(
        self, i: int, r0: int, c0: int, h: int, w: int
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Rows ``r0..r0+h``, columns ``c0..c0+w`` of source ``i`` counted north-up, and its
        mask there (True = valid; None without one): a south-up source's rows are read from
        the bottom and flipped, sample for sample."""
        info = self.spec.sources[i]
        ds = self._dataset(i)
        flip = info.transform[4] > 0
        win = Window(c0, info.height - r0 - h if flip else r0, w, h)
        data = _read(ds.read, self.spec.band, win, info.path)
        mask = _read(ds.read_masks, self.spec.band, win, info.path) != 0 if info.masked else None
        if flip:
            data = data[::-1]
            mask = None if mask is None else mask[::-1]
        return data, mask

    def _check_chosen_nodata(self, data: np.ndarray, valid: np.ndarray | None, i: int) -> None:
        """Refuse a valid sample equal to a nodata value no source declared (the one
        :func:`_mosaic_nodata` chose for gaps and masked samples): it would read as nodata."""
        if not self._chosen:
            return
        spec = self.spec
        same = data == np.asarray(spec.nodata).astype(data.dtype)
        if valid is not None:
            same &= valid
        if same.any():
            path = spec.sources[i].path
            raise SourceError(
                f"{path!r} has valid samples equal to {spec.nodata:g}, the nodata value chosen "
                "for its masked samples or the mosaic's gaps (no source declares one); give "
                f"the source a nodata value no sample takes, e.g. `gdal_translate -a_nodata V "
                f"{os.path.basename(path)} fixed.tif`"
            )

    def read(self, band: int, window: Window) -> np.ndarray:
        """``DatasetReader.read``-like access for one band and a window (what the tiler uses)."""
        if band != self.spec.band:
            raise SourceError(f"this mosaic reads band {self.spec.band}, not band {band}")
        (r0, r1), (c0, c1) = window.toranges()
        return self.read_window(int(r0), int(c0), int(r1 - r0), int(c1 - c0))
