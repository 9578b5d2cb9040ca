"""Many rasters as one DEM, read window by window, optionally reprojected on the fly.

:func:`plan_mosaic` (:mod:`tiler.mosaic_plan`, re-exported here) opens each source once for its
header and returns a picklable :class:`MosaicSpec` (the target grid and every source's footprint
on it), so worker processes can re-open it. :class:`MosaicReader` reads any window of the target
grid: it picks the sources whose footprint meets the window and reads only that part of each
(through a ``WarpedVRT`` when reprojecting). No source is read whole and the mosaic never exists
in memory or on disk; a window costs at most its own size per overlapping source, whatever the
number of files.

Overlap rule: **the first source in the given order that has a valid sample at a position
wins** (like ``rasterio.merge``'s ``first``); later sources only fill the earlier ones' nodata
and gaps. Without reprojection, sources must share CRS, pixel size and pixel grid, so adjacent
SRTM tiles that share their edge row are placed exactly on it. Positions no source covers are
nodata.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import nullcontext

import numpy as np
import rasterio
import rasterio.errors
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.features import geometry_mask
from rasterio.transform import Affine
from rasterio.vrt import WarpedVRT
from rasterio.windows import Window

from tiler.errors import SourceError, SourceReadError, SourceUnavailableError
from tiler.mosaic_plan import (  # noqa: F401  (plan_mosaic re-exported)
    MosaicSpec,
    Ring,
    plan_mosaic,
    seam_rings,
    wrapped_crs,
)
from tiler.source_header import SourceInfo, open_raster, read_info  # noqa: F401  (re-exported)
from tiler.source_http import http_url, is_remote, remote_env, server_failure, slow_advice

MAX_OPEN = 16  # datasets a reader keeps open (least recently used are closed)
WARP_TOLERANCE = 0.01  # source pixels of transform approximation (GDAL: 0.125); see notes
#: held while rasterio's ``geometry_mask`` builds its in-memory raster and while a reprojecting
#: reader opens a source: both hide a warning inside ``warnings.catch_warnings()``, which swaps
#: the process-wide filter list, so two reader threads doing it at once restored each other's
#: list and rasterio's "Dataset has no geotransform" (NotGeoreferencedWarning) escaped, under
#: ``-q`` too (or an "ignore" stayed for good)
_WARNINGS_LOCK = threading.Lock()


def same_nodata(a: float | None, b: float | None) -> bool:
    """True when the nodata values ``a`` and ``b`` mark the same samples (both None, both NaN,
    or equal)."""
    if a is None or b is None:
        return a is None and b is None
    if np.isnan(a) or np.isnan(b):
        return bool(np.isnan(a) and np.isnan(b))
    return float(a) == float(b)


def _valid(data: np.ndarray, nodata: float | None) -> np.ndarray:
    """True where a sample is not nodata (nor NaN); ±inf stays for the tiler's height check."""
    valid = np.ones(data.shape, dtype=bool)
    if data.dtype.kind == "f":
        valid &= ~np.isnan(data)
    if nodata is not None and not np.isnan(nodata):
        valid &= data != np.asarray(nodata).astype(data.dtype)
    return valid


def _inside(rings: list, shape: tuple[int, ...], at: Affine) -> np.ndarray:
    """True where a pixel centre of a ``shape`` window at ``at`` lies in any of ``rings``."""
    shapes = [{"type": "Polygon", "coordinates": [r]} for r in rings]
    with _WARNINGS_LOCK:  # (see there: rasterio's catch_warnings is not thread-safe)
        return geometry_mask(shapes, out_shape=shape, transform=at, invert=True)


def _read(fn: Callable[..., np.ndarray], band: int, win: Window, path: str) -> np.ndarray:
    """``fn(band, window=win)`` (a dataset's ``read`` or ``read_masks``), a GDAL read failure
    raised as :class:`SourceReadError` naming the file and the window (for an ``http(s)`` URL
    whose server fails when asked again, :class:`SourceUnavailableError`)."""
    try:
        return fn(band, window=win)
    except rasterio.errors.RasterioIOError as exc:
        cause: BaseException = exc
        while cause.__cause__ is not None:  # GDAL's first complaint says the most
            cause = cause.__cause__
        rows = f"{int(win.row_off)}..{int(win.row_off + win.height) - 1}"
        cols = f"{int(win.col_off)}..{int(win.col_off + win.width) - 1}"
        where = f"reading {path!r} failed in rows {rows}, columns {cols} of its grid"
        url = http_url(path)
        failure = server_failure(url) if url else None
        if failure is not None:
            raise SourceUnavailableError(
                f"{where}: its server {failure[0]} (GDAL says: {cause}); the server or the "
                "network failed, not the file: check them and rerun the same command to "
                f"resume{slow_advice(failure[0])}"
            ) from exc
        raise SourceReadError(
            f"{where} (GDAL says: {cause}); the file may be truncated or damaged (`gdalinfo "
            "-checksum` reads all of it), or, for a URL, its server failed"
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
        self._remote = [s.path for s in spec.sources if is_remote(s.path)][:1]
        self.height, self.width = spec.height, spec.width
        # the nodata value :func:`_mosaic_nodata` chose (no source declares one), if a sample
        # could take it (not NaN): a valid sample equal to it would read as nodata
        takeable = spec.nodata is not None and not np.isnan(spec.nodata)
        self._chosen = takeable and all(s.nodata is None for s in spec.sources)
        #: per source: the mosaic's nodata differs from its own and a sample could take it (a
        #: valid sample equal to it would read as nodata: refused, as for a chosen one)
        self._foreign = [takeable and not same_nodata(s.nodata, spec.nodata) for s in spec.sources]
        #: per source: its :func:`~tiler.mosaic_plan.seam_rings`, built when a seam is first
        #: filled (the spec names only the sources that meet: rings for every block task
        #: made it ~5x larger)
        self._rings: dict[int, tuple[Ring, tuple[Ring, Ring, Ring]]] = {}
        self._target: CRS | None = None

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
        # (only a reprojecting reader masks by hulls: no other waits for a slow open)
        with _WARNINGS_LOCK if spec.warp else nullcontext():
            ds = open_raster(spec.sources[i].path)
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
                src_crs=wrapped_crs(info),
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
        """Samples of rows ``r0..r0+h`` and columns ``c0..c0+w`` of the target grid (remote
        sources with :func:`~tiler.source_http.remote_env`'s time limits)."""
        with remote_env(*self._remote):
            return self._read_window(r0, c0, h, w)

    def _read_window(self, r0: int, c0: int, h: int, w: int) -> np.ndarray:
        spec = self.spec
        hits = self.sources_for(r0, c0, h, w)
        one = hits[0] if len(hits) == 1 else None
        if (
            one is not None
            and not spec.warp
            and not spec.sources[one].masked
            # its own nodata is the mosaic's (or it has none): its samples need no mapping
            and (
                spec.sources[one].nodata is None
                or same_nodata(spec.sources[one].nodata, spec.nodata)
            )
        ):
            fr0, fc0, fr1, fc1 = (int(v) for v in self._fp[hits[0]])
            if fr0 <= r0 and fc0 <= c0 and r0 + h <= fr1 and c0 + w <= fc1:  # inside one source
                data, _ = self._read_aligned(hits[0], r0 - fr0, c0 - fc0, h, w)
                self._check_chosen_nodata(data, None, hits[0])
                return data.astype(self.dtype, copy=False)
        fill = np.asarray(spec.nodata if spec.nodata is not None else 0).astype(self.dtype)
        out = np.full((h, w), fill, dtype=self.dtype)
        filled = np.zeros((h, w), dtype=bool)
        seams = []  # (source, its samples and their validity before the hull cut, where)
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
            sub = (slice(ir0 - r0, ir1 - r0), slice(ic0 - c0, ic1 - c0))
            if spec.warp and spec.sources[i].hull:
                at = spec.affine * Affine.translation(ic0, ir0)
                if spec.sources[i].near:
                    seams.append((i, data, valid.copy(), sub, at))
                valid &= _inside([spec.sources[i].hull], data.shape, at)
            take = valid & ~filled[sub]
            out[sub][take] = data[take].astype(self.dtype)
            filled[sub] |= take
            if filled.all():
                return out
        for i, data, valid, sub, at in seams:
            # the seam between sources that share no sample lies outside every hull, yet within
            # a source's pixels and a pixel from another's samples, beside them (not past the
            # end of their rows or columns: the mosaic's outer edge stays cut), or a pixel from
            # two others' (where four tiles meet): there its samples (edge-held by GDAL's
            # kernel, as a gdalwarp of the tiles gives) are kept
            todo = valid & ~filled[sub]
            if not todo.any():
                continue
            todo &= _inside([self._seam_rings(i)[0]], data.shape, at)
            beside = np.zeros(data.shape, dtype=bool)
            around = np.zeros(data.shape, dtype=np.int32)
            for j in spec.sources[i].near:
                # a pixel within a neighbour's own pixels is no seam but the rim of an overlap
                # (a source listed twice held edge values past the union's edge: +178 samples)
                todo &= ~_inside([self._seam_rings(j)[0]], data.shape, at)
                cols, rows, both = self._seam_rings(j)[1]
                beside |= _inside([cols, rows], data.shape, at)
                around += _inside([both], data.shape, at)
            take = todo & (beside | (around >= 2))
            out[sub][take] = data[take].astype(self.dtype)
            filled[sub] |= take
        return out

    def _seam_rings(self, i: int) -> tuple[Ring, tuple[Ring, Ring, Ring]]:
        """Source ``i``'s :func:`~tiler.mosaic_plan.seam_rings` on the target (built once per
        reader)."""
        rings = self._rings.get(i)
        if rings is None:
            if self._target is None:
                self._target = CRS.from_wkt(self.spec.crs_wkt)
            rings = self._rings[i] = seam_rings(self.spec.sources[i], self._target)
        return rings

    def _read_aligned(
        self, i: int, r0: int, c0: int, h: int, w: int
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Rows ``r0..r0+h``, columns ``c0..c0+w`` of source ``i`` counted north-up from the
        west, and its mask there (True = valid; None without one): a south-up source's rows
        are read from the bottom and flipped, sample for sample (columns running east to west
        likewise)."""
        info = self.spec.sources[i]
        ds = self._dataset(i)
        flip, mirror = info.transform[4] > 0, info.transform[0] < 0
        win = Window(
            info.width - c0 - w if mirror else c0, info.height - r0 - h if flip else r0, w, h
        )
        data = _read(ds.read, self.spec.band, win, info.path)
        mask = _read(ds.read_masks, self.spec.band, win, info.path) != 0 if info.masked else None
        if flip or mirror:
            turn = (slice(None, None, -1 if flip else 1), slice(None, None, -1 if mirror else 1))
            data = data[turn]
            mask = None if mask is None else mask[turn]
        return data, mask

    def _check_chosen_nodata(self, data: np.ndarray, valid: np.ndarray | None, i: int) -> None:
        """Refuse a valid sample equal to a nodata value no source declared (the one
        :func:`_mosaic_nodata` chose for gaps and masked samples): it would read as nodata."""
        if not self._chosen and not self._foreign[i]:
            return
        spec = self.spec
        same = data == np.asarray(spec.nodata).astype(data.dtype)
        if valid is not None:
            same &= valid
        if same.any() and not self._chosen:
            path = spec.sources[i].path
            first = next(s.path for s in spec.sources if s.nodata is not None)
            raise SourceError(
                f"{path!r} has valid samples equal to {spec.nodata:g}, the mosaic's nodata value "
                f"(declared by {os.path.basename(first)!r}, the first source with one): they "
                "would read as nodata; give the sources one nodata value no valid sample takes, "
                f"e.g. `gdal_translate -a_nodata V {os.path.basename(path)} fixed.tif`"
            )
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
