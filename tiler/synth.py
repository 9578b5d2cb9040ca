"""Deterministic fractal DEMs of any size, written window by window in bounded memory.

Method
------
Every sample is a pure function of its global ``(row, col)``, the seed, the raster size, ``relief``
and ``base``. Coordinates are normalised by the raster size (``u = col / (size - 1)``), so two sizes
show the same landscape at two resolutions (in samples: the GeoTIFF's cells are ``cell_size``
metres whatever the size, so a larger raster spreads that landscape over more ground unless
``cell_size`` shrinks with it); a larger raster only adds finer octaves.

Each octave ``o`` is 2-D gradient (Perlin) noise on an integer lattice of ``2 * 2**o`` cells across
the raster (lacunarity 2), shifted by a seed-derived sub-cell offset so the octaves' lattices do
not line up. A lattice point's gradient is one of 64 unit vectors chosen by a splitmix64 hash of
``(ix, iy, octave, seed)`` computed in ``uint64`` numpy arithmetic; interpolation uses the quintic
fade ``6t^5 - 15t^4 + 10t^3``. Octaves are added while their wavelength is at least 4 samples, up
to 12 of them. Roles by octave:

* octaves 0-1, fBm with gain 0.5: the continental shape (lowlands, uplands);
* octaves 2-6, ridged multifractal (``(1 - |n|)^2`` weighted by the previous octave's ridge):
  the mountain ranges, faded in where the continental shape is high;
* octaves 7 and up, fBm with gain 0.5: small-scale roughness, stronger in the mountains.

The sum is shaped into ``t`` (about 0 in the deepest valleys to 1 on the highest peaks) and the
elevation is ``base + relief * t``. ``int16`` rounds half to even (``np.round``) and clips;
``float32`` keeps fractional metres.

Gradient noise is separable along the two axes, so an octave is evaluated as a handful of
gathers and products of per-row and per-column vectors instead of per-sample hashing. Only
element-wise IEEE operations (no BLAS, no reductions, no transcendental functions per sample) are
used, which is what makes a sample bit-for-bit identical however the raster is split into windows.
A window is computed in strips of about 64 K samples that stay in cache, so the memory used is a
few MB per window whatever the raster size.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.windows import Window

from tiler.atomic import raster_written_whole
from tiler.errors import SourceError

__all__ = ["DTYPES", "synth_array", "synth_dem"]

DTYPES = ("int16", "float32")
"""The sample types ``synth_dem`` writes."""

_ARRAY_DTYPES = ("int16", "float32", "float64")
_BASE_CELLS = 2  # lattice cells across the raster at octave 0
_MIN_WAVELENGTH = 4.0  # finest octave kept, in samples
_MAX_OCTAVES = 12
_CONTINENT = 2  # octaves [0, _CONTINENT) shape the continent
_RIDGED_END = 7  # octaves [_CONTINENT, _RIDGED_END) are ridged; later ones are detail
_STRIP_SAMPLES = 1 << 16
_BLOCK = 512

_M64 = (1 << 64) - 1
_KX = np.uint64(0x9E3779B97F4A7C15)
_KY = np.uint64(0xC2B2AE3D27D4EB4F)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S58 = (np.uint64(s) for s in (30, 27, 31, 58))
_ANGLES = 2.0 * np.pi * (np.arange(64) + 0.5) / 64.0
_GRAD_X = np.cos(_ANGLES)
_GRAD_Y = np.sin(_ANGLES)


def _splitmix64(x: int) -> int:
    """Scalar splitmix64 step on Python ints (seed and octave keys)."""
    x = (x + 0x9E3779B97F4A7C15) & _M64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _M64
    return x ^ (x >> 31)


def _mix(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array, in place."""
    h ^= h >> _S30
    h *= _MIX1
    h ^= h >> _S27
    h *= _MIX2
    h ^= h >> _S31
    return h


@dataclass(frozen=True)
class _Octave:
    scale: float  # lattice cells per sample
    off_x: float
    off_y: float
    key: np.uint64
    amp: float


@lru_cache(maxsize=64)
def _plan(size: int, seed: int) -> tuple[_Octave, ...]:
    """The octaves used for a raster of ``size`` samples a side."""
    cells = (size - 1) / _MIN_WAVELENGTH / _BASE_CELLS
    count = 1 if cells < 2 else min(_MAX_OCTAVES, int(math.floor(math.log2(cells))) + 1)
    seed_key = _splitmix64(seed & _M64)
    octaves = []
    for o in range(count):
        k1 = _splitmix64(seed_key ^ (o * 0xD6E8FEB86659FD93 & _M64))
        k2 = _splitmix64(k1)
        k3 = _splitmix64(k2)
        octaves.append(
            _Octave(
                scale=_BASE_CELLS * 2.0**o / (size - 1),
                off_x=(k2 >> 11) * 2.0**-53,
                off_y=(k3 >> 11) * 2.0**-53,
                key=np.uint64(k1),
                amp=0.5**o,
            )
        )
    return tuple(octaves)


def _axis(start: int, n: int, scale: float, offset: float):
    """Lattice cell, fraction and faded fraction of ``n`` consecutive samples from ``start``."""
    x = np.arange(start, start + n, dtype=np.int64).astype(np.float64)
    x *= scale
    x += offset
    cell = np.floor(x)
    f = x - cell
    fade = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)
    return cell.astype(np.int64), f, fade


class _ColumnTerms:
    """Per-column quantities of one octave over one window (shared by all its strips)."""

    def __init__(self, octave: _Octave, c0: int, nc: int) -> None:
        ix, fx, sx = _axis(c0, nc, octave.scale, octave.off_x)
        self.lx0 = int(ix[0])
        self.hx = np.arange(self.lx0, int(ix[-1]) + 2, dtype=np.int64).astype(np.uint64) * _KX
        self.jx0 = ix - self.lx0
        self.jx1 = self.jx0 + 1
        amp = octave.amp
        self.wa0 = (1.0 - sx) * fx * amp
        self.wa1 = sx * (fx - 1.0) * amp
        self.wb0 = (1.0 - sx) * amp
        self.wb1 = sx * amp


def _octave_noise(
    out: np.ndarray, tmp: np.ndarray, octave: _Octave, cols: _ColumnTerms, r0: int
) -> None:
    """Write ``amp * noise`` of one octave for rows ``r0 .. r0 + len(out)`` into ``out``."""
    nr = out.shape[0]
    iy, fy, sy = _axis(r0, nr, octave.scale, octave.off_y)
    ly0 = int(iy[0])
    hy = np.arange(ly0, int(iy[-1]) + 2, dtype=np.int64).astype(np.uint64) * _KY
    hy ^= octave.key
    g = (_mix(hy[:, None] + cols.hx[None, :]) >> _S58).astype(np.intp)
    gx = _GRAD_X[g]
    gy = _GRAD_Y[g]
    # Along x: a = sum_i w_i(x) (x - i) gx_i, b = sum_i w_i(x) gy_i, for every lattice row.
    a = gx[:, cols.jx0] * cols.wa0 + gx[:, cols.jx1] * cols.wa1
    b = gy[:, cols.jx0] * cols.wb0 + gy[:, cols.jx1] * cols.wb1
    # Along y: noise = a0 + fy b0 + sy (a1 - a0 - b1) + sy fy (b1 - b0).
    p = a[:-1]
    q = b[:-1]
    r = a[1:] - a[:-1]
    r -= b[1:]
    s = b[1:] - b[:-1]
    jy = iy - ly0
    np.take(p, jy, axis=0, out=out)
    np.take(q, jy, axis=0, out=tmp)
    tmp *= fy[:, None]
    out += tmp
    np.take(r, jy, axis=0, out=tmp)
    tmp *= sy[:, None]
    out += tmp
    np.take(s, jy, axis=0, out=tmp)
    tmp *= (sy * fy)[:, None]
    out += tmp


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Cubic smoothstep of ``x`` from ``lo`` to ``hi``, in place."""
    x -= lo
    x *= 1.0 / (hi - lo)
    np.clip(x, 0.0, 1.0, out=x)
    x *= x * (3.0 - 2.0 * x)
    return x


def _strip_t(r0: int, nr: int, plan: tuple[_Octave, ...], cols: list[_ColumnTerms]) -> np.ndarray:
    """Normalised height ``t`` of rows ``r0 .. r0 + nr`` (columns given by ``cols``)."""
    nc = cols[0].jx0.shape[0]
    noise = np.empty((nr, nc))
    tmp = np.empty((nr, nc))
    cont = np.zeros((nr, nc))
    ridge = np.zeros((nr, nc))
    detail = np.zeros((nr, nc))
    weight = np.ones((nr, nc))
    for o, (octave, col) in enumerate(zip(plan, cols, strict=True)):
        _octave_noise(noise, tmp, octave, col, r0)
        if o < _CONTINENT:
            cont += noise
        elif o < _RIDGED_END:
            # Ridged multifractal: signal = (1 - |n|)^2, weighted by the previous signal.
            np.abs(noise, out=noise)
            noise *= -1.5 / octave.amp
            noise += 1.0
            np.maximum(noise, 0.0, out=noise)
            noise *= noise
            noise *= weight
            np.multiply(noise, 2.0, out=weight)
            np.minimum(weight, 1.0, out=weight)
            noise *= octave.amp
            ridge += noise
        else:
            detail += noise
    mask = _smoothstep(cont.copy(), -0.05, 0.35)
    t = cont
    t *= 0.5
    t += 0.3
    ridge *= mask
    ridge *= 0.6
    t += ridge
    mask *= 1.5
    mask += 0.5
    detail *= mask
    t += detail
    return t


def _check_slice(s: slice, size: int, what: str) -> tuple[int, int]:
    if not isinstance(s, slice) or s.step not in (None, 1):
        raise SourceError(f"Expected {what} to be a slice with step 1, got {s!r}.")
    start = 0 if s.start is None else int(s.start)
    stop = size if s.stop is None else int(s.stop)
    if not 0 <= start <= stop <= size:
        raise SourceError(f"Expected {what} within 0..{size}, got {s!r}.")
    return start, stop


#: the largest side :func:`synth_dem` writes: 1.1e12 samples, 2 TiB as int16 (beyond it
#: GDAL refuses the GeoTIFF's tile arrays, after the file was created)
MAX_SYNTH_SIZE = 2**20 + 1


def _check_size(size: int) -> int:
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 2:
        raise SourceError(f"Expected the DEM size to be an integer >= 2, got {size!r}.")
    if size > MAX_SYNTH_SIZE:
        raise SourceError(
            f"size {size:,} is beyond the {MAX_SYNTH_SIZE:,} samples per side synth writes "
            f"({float(size) ** 2:.3g} samples); give at most {MAX_SYNTH_SIZE}"
        )
    return int(size)


#: the finest ``cell_size`` (m): finer cells could not be told apart at the origin's
#: coordinates (500000, 5000000) in a GeoTIFF's float64 transform, and 1e-300 wrote bounds
#: of ±0 width
MIN_CELL_SIZE = 1e-6
#: the widest DEM (m, size x cell_size): the Earth's circumference; a larger extent is no
#: place on Earth (1e308 m cells wrote a GeoTIFF with infinite bounds)
MAX_EXTENT_M = 4e7


def check_extent(
    size: int, cell_size: float, origin: tuple[float, float] = (500000.0, 5000000.0)
) -> float:
    """``cell_size`` if a ``size`` x ``size`` DEM of such cells from ``origin`` has finite,
    representable bounds: at least :data:`MIN_CELL_SIZE`, and ``size`` x ``cell_size`` at
    most :data:`MAX_EXTENT_M`; else :class:`SourceError` naming the value and what to give
    (``size`` is checked first: beyond :data:`MAX_SYNTH_SIZE`, that is the error)."""
    size = _check_size(size)
    try:
        c = float(cell_size)
    except (TypeError, ValueError):
        raise SourceError(f"Expected a positive cell size, got {cell_size!r}.") from None
    if isinstance(cell_size, bool) or not (math.isfinite(c) and c > 0):
        raise SourceError(f"Expected a positive cell size, got {cell_size!r}.")
    if not all(math.isfinite(float(o)) for o in origin):
        raise SourceError(f"Expected a finite origin, got {origin!r}.")
    if c < MIN_CELL_SIZE:
        raise SourceError(
            f"cell size {c:g} m is finer than {MIN_CELL_SIZE:g} m: the DEM's bounds could not "
            f"be told apart from its origin; give a cell size of at least {MIN_CELL_SIZE:g} m"
        )
    extent = size * c
    if not (math.isfinite(extent) and extent <= MAX_EXTENT_M):
        raise SourceError(
            f"cell size {c:g} m makes the {size:,}-sample DEM {extent:g} m wide, beyond "
            f"{MAX_EXTENT_M:g} m (the Earth's circumference); give a cell size of at most "
            f"{MAX_EXTENT_M / size:g} m for this size"
        )
    return c


def synth_array(
    rows: slice,
    cols: slice,
    size: int,
    seed: int = 0,
    relief: float = 2500.0,
    base: float = 200.0,
    dtype: str = "float32",
) -> np.ndarray:
    """Samples ``[rows, cols]`` of the ``size`` x ``size`` synthetic DEM, as ``dtype``.

    The result does not depend on how the raster is split; ``dtype`` is int16, float32 or float64.
    """
    size = _check_size(size)
    if dtype not in _ARRAY_DTYPES:
        raise SourceError(f"Expected dtype to be one of {', '.join(_ARRAY_DTYPES)}, got {dtype!r}.")
    r0, r1 = _check_slice(rows, size, "rows")
    c0, c1 = _check_slice(cols, size, "cols")
    nr, nc = r1 - r0, c1 - c0
    result = np.empty((nr, nc), dtype=dtype)
    if nr == 0 or nc == 0:
        return result
    plan = _plan(size, int(seed))
    col_terms = [_ColumnTerms(octave, c0, nc) for octave in plan]
    strip = max(1, _STRIP_SAMPLES // nc)
    relief = float(relief)
    base = float(base)
    for s0 in range(r0, r1, strip):
        n = min(strip, r1 - s0)
        z = _strip_t(s0, n, plan, col_terms)
        z *= relief
        z += base
        out = result[s0 - r0 : s0 - r0 + n]
        if dtype == "int16":
            np.round(z, out=z)
            np.clip(z, -32768.0, 32767.0, out=z)
        out[...] = z
    return result


def synth_dem(
    path: str | os.PathLike,
    size: int,
    seed: int = 0,
    dtype: str = "int16",
    *,
    window: int = 1024,
    relief: float = 2500.0,
    base: float = 200.0,
    cell_size: float = 30.0,
    origin: tuple[float, float] = (500000.0, 5000000.0),
    crs: str = "EPSG:32633",
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Write a deterministic fractal DEM (size x size, int16 or float32 GeoTIFF) window by window.

    Memory stays at one ``window``-row strip whatever ``size`` is; the samples equal
    :func:`synth_array`'s for the same arguments.
    """
    size = _check_size(size)
    if dtype not in DTYPES:
        raise SourceError(f"Expected dtype to be one of {', '.join(DTYPES)}, got {dtype!r}.")
    if isinstance(window, bool) or not isinstance(window, int) or window < 16:
        raise SourceError(f"Expected window to be an integer >= 16, got {window!r}.")
    cell_size = check_extent(size, cell_size, origin)
    profile = {
        "driver": "GTiff",
        "width": size,
        "height": size,
        "count": 1,
        "dtype": dtype,
        "crs": crs,
        "transform": Affine(cell_size, 0.0, origin[0], 0.0, -cell_size, origin[1]),
        "nodata": None,
        "compress": "deflate",
        "predictor": 2 if dtype == "int16" else 3,
        "BIGTIFF": "IF_SAFER",
    }
    if size >= _BLOCK:
        profile.update(tiled=True, blockxsize=_BLOCK, blockysize=_BLOCK)
    total = size * size
    done = 0
    # written beside ``path`` and renamed once read back whole: an interrupted or failed run
    # (Ctrl-C, a full disk) leaves no DEM that looks complete (GDAL fills unwritten tiles with
    # 0 when the file is closed), and a ``path`` being replaced stays as it was until then
    with raster_written_whole(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        for r0 in range(0, size, window):
            nr = min(window, size - r0)
            for c0 in range(0, size, window):
                nc = min(window, size - c0)
                arr = synth_array(
                    slice(r0, r0 + nr), slice(c0, c0 + nc), size, seed, relief, base, dtype
                )
                dst.write(arr, 1, window=Window(c0, r0, nc, nr))
                done += nr * nc
                if progress is not None:
                    progress(done, total)
