"""Lossless level encodings and nodata filling for one block (pure numpy, no I/O).

Level ``i >= 1`` values are predicted by interpolating the level ``i-1`` grid (edge midpoints:
mean of the two ends, centres: mean of the four corners). What is stored is the prediction
residual, which is exactly invertible:

* integer DEMs (``int-residual``): ``v - floor(prediction)`` in the source dtype's modular
  arithmetic (wraps like two's complement, so it never overflows), zigzag-mapped to the
  same-size unsigned type (0, -1, 1, -2... become 0, 1, 2, 3...) so small residuals have zero
  high bytes; level 0 holds the zigzagged values themselves;
* float DEMs (``float-xor``): the bit pattern of ``v`` XOR the bit pattern of the prediction
  rounded to the source dtype — the high bits cancel, so the result compresses;
* quantised floats (``--precision``): ``round(v / step)`` as int32, then ``int-residual``.

Nodata (and NaN, and padding) samples are replaced, coarse to fine, by the prediction from the
coarser level, so they never make spikes and their residual is zero; a mask keeps them apart.
"""

from __future__ import annotations

import numpy as np

from tiler import kernels
from tiler.errors import SourceError
from tiler.layout import (
    decompose,
    grid_side,
    level_end,
    level_size,
    level_start,
    reconstruct,
    subgrid,
)

INT_RESIDUAL = "int-residual"
FLOAT_XOR = "float-xor"

SUPPORTED_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")
_UINT_VIEW = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}
_INT_VIEW = {1: np.int8, 2: np.int16, 4: np.int32, 8: np.int64}


def parse_dtype(dtype: np.dtype | str) -> np.dtype:
    """Validate a source dtype the tiler can store losslessly."""
    dt = np.dtype(dtype)
    if dt.name not in SUPPORTED_DTYPES:
        raise SourceError(
            f"Unsupported raster dtype {dt.name}; supported: {', '.join(SUPPORTED_DTYPES)}. "
            "Convert the band first (e.g. gdal_translate -ot Int32)."
        )
    return dt


def storage_dtype_for(dtype: np.dtype) -> np.dtype:
    """The dtype levels are stored in: the same-size unsigned integer (zigzag or float bits)."""
    return np.dtype(_UINT_VIEW[np.dtype(dtype).itemsize])


def zigzag(signed: np.ndarray) -> np.ndarray:
    """Map signed integers to unsigned ones of the same size: 0,-1,1,-2 -> 0,1,2,3."""
    bits = signed.dtype.itemsize * 8
    u = _UINT_VIEW[signed.dtype.itemsize]
    return ((signed << 1) ^ (signed >> (bits - 1))).view(u)


def unzigzag(z: np.ndarray) -> np.ndarray:
    """Inverse of :func:`zigzag` (returns the signed type of the same size)."""
    s = _INT_VIEW[z.dtype.itemsize]
    return ((z >> 1) ^ (-(z & 1).view(s)).view(z.dtype)).view(s)


def _to_stored0(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if dtype.kind == "f":
        return values.view(_UINT_VIEW[dtype.itemsize])
    return zigzag(values.view(_INT_VIEW[dtype.itemsize]))


def _from_stored0(stored: np.ndarray, dtype: np.dtype) -> np.ndarray:
    st = np.asarray(stored).view(_UINT_VIEW[dtype.itemsize])
    if dtype.kind == "f":
        return st.view(dtype).copy()
    return unzigzag(st).view(dtype).copy()


def encoding_for(dtype: np.dtype) -> str:
    """The lossless level encoding used for a source (or quantised) dtype."""
    return FLOAT_XOR if np.dtype(dtype).kind == "f" else INT_RESIDUAL


def _work_dtype(dtype: np.dtype) -> type:
    """Arithmetic type for predictions: int32 is exact for sums of four 16-bit values."""
    if dtype.kind == "f":
        return np.float64
    return np.int32 if dtype.itemsize <= 2 else np.int64


def _predict_parts(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predictions for the vertices a ``(m, m)`` grid gains at the next level.

    Returns ``(h, v, c)``: horizontal edge midpoints ``(m, m-1)``, vertical ones ``(m-1, m)``
    and centres ``(m-1, m-1)``. Integers floor in a wide integer type; floats take means.
    """
    wt = _work_dtype(g.dtype)
    w = g.astype(wt, copy=False)
    if g.dtype.kind == "f":
        h = (w[:, :-1] + w[:, 1:]) * 0.5
        v = (w[:-1, :] + w[1:, :]) * 0.5
        c = (w[:-1, :-1] + w[:-1, 1:] + w[1:, :-1] + w[1:, 1:]) * 0.25
        return h, v, c
    h = (w[:, :-1] + w[:, 1:]) >> 1
    v = (w[:-1, :] + w[1:, :]) >> 1
    c = (w[:-1, :-1] + w[:-1, 1:] + w[1:, :-1] + w[1:, 1:]) >> 2
    return h, v, c


def predict(coarse: np.ndarray) -> np.ndarray:
    """Interpolate a ``(m, m)`` grid to the ``(2m-1, 2m-1)`` grid of the next level.

    Integers use floor division (exact, in a wide type); floats use float64 means.
    """
    h, v, c = _predict_parts(coarse)
    m = coarse.shape[0]
    out = np.empty((2 * m - 1, 2 * m - 1), dtype=h.dtype)
    out[::2, ::2] = coarse
    out[::2, 1::2] = h
    out[1::2, ::2] = v
    out[1::2, 1::2] = c
    return out


def _split(seq: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Views of a level's values (sequence order) by position in the ``2m-1`` grid.

    Row-major order alternates an even row's odd columns (``m-1`` values) with a whole odd row
    (``2m-1`` values), ending with the last even row. Returns ``(h_head, v, c, h_tail)``:
    even rows but the last ``(m-1, m-1)``, odd rows' even columns ``(m-1, m)``, odd rows' odd
    columns ``(m-1, m-1)``, and the last even row ``(m-1,)``.
    """
    n = (m - 1) * (3 * m - 2)
    head = seq[:n].reshape(m - 1, 3 * m - 2)
    odd = head[:, m - 1 :]
    return head[:, : m - 1], odd[:, ::2], odd[:, 1::2], seq[n:]


def _join(parts: tuple[np.ndarray, ...], m: int, dtype: np.dtype) -> np.ndarray:
    """Inverse of :func:`_split` for ``(h, v, c)`` parts of a level (``h`` is ``(m, m-1)``)."""
    h, v, c = parts
    out = np.empty((m - 1) * (3 * m - 2) + (m - 1), dtype=dtype)
    hh, vv, cc, tail = _split(out, m)
    hh[...] = h[:-1]
    vv[...] = v
    cc[...] = c
    tail[...] = h[-1]
    return out


def fill_invalid(grid: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Replace invalid samples, coarse to fine, by the coarser level's prediction.

    Level-0 corners that are invalid take the mean of the block's valid samples (0 if none).
    Returns a new array of the grid's dtype; valid samples are unchanged.
    """
    if valid.all():
        return grid.copy()
    fill0 = float(np.mean(grid[valid], dtype=np.float64)) if valid.any() else 0.0
    mod = kernels.active()
    if mod is not None and grid.shape == (grid_side(k),) * 2:
        return kernels.fill(
            mod, grid, valid, k, fill0 if grid.dtype.kind == "f" else np.floor(fill0)
        )
    return _fill_invalid_numpy(grid, valid, k, fill0)


def fill_invalid_numpy(grid: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Reference (numpy) form of :func:`fill_invalid`."""
    if valid.all():
        return grid.copy()
    fill0 = float(np.mean(grid[valid], dtype=np.float64)) if valid.any() else 0.0
    return _fill_invalid_numpy(grid, valid, k, fill0)


def _fill_invalid_numpy(grid: np.ndarray, valid: np.ndarray, k: int, fill0: float) -> np.ndarray:
    dtype = grid.dtype
    g = subgrid(grid, k, 0).copy()
    v0 = subgrid(valid, k, 0)
    if dtype.kind == "f":
        g[~v0] = fill0
    else:
        g[~v0] = int(np.floor(fill0))
    for level in range(1, k + 1):
        pred = predict(g)
        nxt = subgrid(grid, k, level).copy()
        bad = ~subgrid(valid, k, level)
        nxt[bad] = pred[bad].astype(dtype)
        nxt[::2, ::2] = g
        g = nxt
    return g


def encode_levels(grid: np.ndarray, k: int) -> list[np.ndarray]:
    """Residual-encode a (filled) ``2**k+1`` block into ``k+1`` level arrays.

    The arrays have the same-size unsigned dtype (:func:`storage_dtype_for`); with the compiled
    kernels they are consecutive views of one buffer (the block's sequence).
    """
    if grid.shape != (grid_side(k),) * 2:
        raise ValueError(f"expected a {grid_side(k)}x{grid_side(k)} block, got {grid.shape}")
    mod = kernels.active()
    if mod is None:
        return encode_levels_numpy(grid, k)
    seq = kernels.encode(mod, grid, k)
    return [seq[level_start(i) : level_end(i) + 1] for i in range(k + 1)]


def encode_levels_numpy(grid: np.ndarray, k: int) -> list[np.ndarray]:
    """Reference (numpy) form of :func:`encode_levels`."""
    dtype = grid.dtype
    if grid.shape != (grid_side(k),) * 2:
        raise ValueError(f"expected a {grid_side(k)}x{grid_side(k)} block, got {grid.shape}")
    out = [_to_stored0(subgrid(grid, k, 0).ravel().copy(), dtype)]
    for level in range(1, k + 1):
        coarse = subgrid(grid, k, level - 1)
        fine = subgrid(grid, k, level)
        m = coarse.shape[0]
        pred = _join(_predict_parts(coarse), m, _work_dtype(dtype))
        vals = _join((fine[::2, 1::2], fine[1::2, ::2], fine[1::2, 1::2]), m, dtype)
        out.append(_residual(vals, pred, dtype))
    return out


def _residual(vals: np.ndarray, pred: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if dtype.kind == "f":
        u = _UINT_VIEW[dtype.itemsize]
        return vals.view(u) ^ pred.astype(dtype).view(u)
    wide = vals.astype(pred.dtype) - pred
    return zigzag(wide.astype(_INT_VIEW[dtype.itemsize]))


def _unresidual(res: np.ndarray, pred: np.ndarray, dtype: np.dtype, out: np.ndarray) -> None:
    """Write into ``out`` (a view of the grid, of ``dtype``) the values whose stored residuals
    are ``res``, from their predictions ``pred`` (wide type): the inverse of :func:`_residual`,
    in as few numpy calls as it takes (the small levels cost calls, not samples)."""
    u = _UINT_VIEW[dtype.itemsize]
    if dtype.kind == "f":
        np.bitwise_xor(res.view(u), pred.astype(dtype).view(u), out=out.view(u))
        return
    z = res.view(u)  # unzigzag, in place on two temporaries
    sign = z & 1
    np.negative(sign, out=sign)
    r = z >> 1
    np.bitwise_xor(r, sign, out=r)
    # the sum in the wide type, wrapped to ``dtype`` on the way out: what ``astype(dtype)`` of
    # the wide sum gives (mod 2**bits), without the two casts
    np.add(r.view(_INT_VIEW[dtype.itemsize]), pred, out=out, casting="unsafe")


def _next_grid(g: np.ndarray, raw: np.ndarray, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """The next level's grid from this one and its stored values; also its decoded values."""
    m = g.shape[0]
    h, v, c = _predict_parts(g)
    rh, rv, rc, rt = _split(np.asarray(raw), m)
    out = np.empty((2 * m - 1, 2 * m - 1), dtype=dtype)
    out[::2, ::2] = g
    _unresidual(rh, h[:-1], dtype, out[0 : 2 * m - 2 : 2, 1::2])
    _unresidual(rt, h[-1], dtype, out[2 * m - 2, 1::2])
    _unresidual(rv, v, dtype, out[1::2, ::2])
    _unresidual(rc, c, dtype, out[1::2, 1::2])
    return out


def decode_grid(
    stored: list[np.ndarray],
    dtype: np.dtype,
    level: int | None = None,
    extent: tuple[int, int] | None = None,
    work: np.ndarray | None = None,
) -> np.ndarray:
    """The ``2**L+1`` grid of level ``L`` from the stored (residual) levels ``0..L``.

    ``extent=(rows, cols)``: only the grid's top-left ``rows x cols`` (e.g. the part of an edge
    block inside the DEM), decoded alone and returned as a new array; ``work``, an optional
    ``2**L+1`` square array of ``dtype`` the compiled decoder may use as scratch for it.
    """
    dtype = np.dtype(dtype)
    if level is None:
        level = len(stored) - 1
    side = grid_side(level)
    ext = window_extent(extent, side)
    mod = kernels.active(load=False)
    if mod is not None and _sizes_ok(stored, level):
        reuse = ext is not None and work is not None and work.shape == (side, side)
        g = work if reuse and work.dtype == dtype else np.empty((side, side), dtype=dtype)
        kernels.decode(mod, joined(stored, level), g, level, 0, ext)
        return g if ext is None else g[: ext[0], : ext[1]].copy()
    return decode_grid_numpy(stored, dtype, level, ext)


def window_extent(extent: tuple[int, int] | None, side: int) -> tuple[int, int] | None:
    """``extent`` checked against a ``side``-square grid; None when it is the whole grid."""
    if extent is None:
        return None
    rows, cols = (int(v) for v in extent)
    if not (1 <= rows <= side and 1 <= cols <= side):
        raise ValueError(f"extent {extent!r} is outside the {side}x{side} grid (1..{side} each)")
    return None if rows == cols == side else (rows, cols)


def joined(stored: list[np.ndarray], level: int) -> np.ndarray:
    """Levels ``0..level`` as one sequence: a view when they are consecutive views of one array
    (what ``TerrainStore`` reads and the compiled encoder returns), else a concatenated copy."""
    parts = [np.asarray(s) for s in stored[: level + 1]]
    base = parts[0].base
    if (
        isinstance(base, np.ndarray)
        and base.ndim == 1
        and base.flags.c_contiguous
        and all(p.base is base and p.ndim == 1 and p.flags.c_contiguous for p in parts)
        and all(p.dtype == base.dtype for p in parts)
    ):
        size = base.dtype.itemsize
        ptr = [p.__array_interface__["data"][0] for p in parts]  # (ctypes.data is ~3x slower)
        at = ptr[0]
        start, rem = divmod(at - base.__array_interface__["data"][0], size)
        if rem == 0 and all(
            ptr[i] == at + level_start(i) * size and p.size == level_size(i)
            for i, p in enumerate(parts)
        ):
            return base[start : start + level_end(level) + 1]
    return np.concatenate(parts)


def _sizes_ok(stored: list[np.ndarray], level: int) -> bool:
    """Whether levels ``0..level`` have the layout's sizes (else numpy raises the error)."""
    return len(stored) > level >= 0 and all(
        np.size(stored[i]) == level_end(i) - level_start(i) + 1 for i in range(level + 1)
    )


def decode_grid_numpy(
    stored: list[np.ndarray],
    dtype: np.dtype,
    level: int | None = None,
    extent: tuple[int, int] | None = None,
) -> np.ndarray:
    """Reference (numpy) form of :func:`decode_grid`."""
    dtype = np.dtype(dtype)
    if level is None:
        level = len(stored) - 1
    ext = window_extent(extent, grid_side(level))
    g = _from_stored0(stored[0], dtype).reshape(2, 2)
    if ext is None:
        for i in range(1, level + 1):
            g = _next_grid(g, stored[i], dtype)
        return g
    rows, cols = ext

    def need(n: int, i: int) -> int:  # last level-i vertex index that covers 0..n-1 at ``level``
        s = 1 << (level - i)
        return (n - 1 + s - 1) // s

    g = g[: need(rows, 0) + 1, : need(cols, 0) + 1]
    for i in range(1, level + 1):
        g = _next_window(g, stored[i], dtype, (1 << (i - 1)) + 1)
        g = g[: need(rows, i) + 1, : need(cols, i) + 1]
    return np.ascontiguousarray(g)


def _next_window(g: np.ndarray, raw: np.ndarray, dtype: np.dtype, m: int) -> np.ndarray:
    """:func:`_next_grid` for the top-left ``(a+1, b+1)`` vertices ``g`` of an ``(m, m)`` grid:
    the next level's top-left ``(2a+1, 2b+1)`` (the stored values past it are not read)."""
    a, b = g.shape[0] - 1, g.shape[1] - 1
    h, v, c = _predict_parts(g)
    rh, rv, rc, rt = _split(np.asarray(raw), m)
    out = np.empty((2 * a + 1, 2 * b + 1), dtype=dtype)
    out[::2, ::2] = g
    head = min(a + 1, m - 1)  # even rows held in ``rh``; the last even row is ``rt``
    _unresidual(rh[:head, :b], h[:head], dtype, out[0 : 2 * head : 2, 1::2])
    if a == m - 1:
        _unresidual(rt[:b], h[-1], dtype, out[2 * a, 1::2])
    _unresidual(rv[:a, : b + 1], v, dtype, out[1::2, ::2])
    _unresidual(rc[:a, :b], c, dtype, out[1::2, 1::2])
    return out


def level_values(grid: np.ndarray) -> np.ndarray:
    """The values a level's ``(2m-1, 2m-1)`` grid adds, in sequence (row-major) order."""
    m = (grid.shape[0] + 1) // 2
    return _join((grid[::2, 1::2], grid[1::2, ::2], grid[1::2, 1::2]), m, grid.dtype)


def decode_levels(stored: list[np.ndarray], dtype: np.dtype) -> list[np.ndarray]:
    """Decoded (height) values of each stored level, in sequence order."""
    dtype = np.dtype(dtype)
    last = len(stored) - 1
    if kernels.active(load=False) is not None and _sizes_ok(stored, last):
        return [lv.copy() for lv in decompose(decode_grid(stored, dtype, last), last)]
    return decode_levels_numpy(stored, dtype)


def decode_levels_numpy(stored: list[np.ndarray], dtype: np.dtype) -> list[np.ndarray]:
    """Reference (numpy) form of :func:`decode_levels`."""
    dtype = np.dtype(dtype)
    out = [_from_stored0(stored[0], dtype)]
    g = out[0].reshape(2, 2)
    for i in range(1, len(stored)):
        g = _next_grid(g, stored[i], dtype)
        out.append(level_values(g))
    return out


def decode_next_level(levels: list[np.ndarray], raw: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Decode level ``len(levels)`` from its stored values and the decoded levels before it."""
    dtype = np.dtype(dtype)
    n = len(levels)
    if n == 0:
        return _from_stored0(raw, dtype)
    mod = kernels.active(load=False)
    if mod is not None and np.size(raw) == level_end(n) - level_start(n) + 1:
        g = np.empty((grid_side(n),) * 2, dtype=dtype)
        g[::2, ::2] = reconstruct(levels, n - 1)
        kernels.decode(mod, np.asarray(raw), g, n, n)
        return level_values(g)
    return decode_next_level_numpy(levels, raw, dtype)


def decode_next_level_numpy(
    levels: list[np.ndarray], raw: np.ndarray, dtype: np.dtype
) -> np.ndarray:
    """Reference (numpy) form of :func:`decode_next_level`."""
    dtype = np.dtype(dtype)
    n = len(levels)
    if n == 0:
        return _from_stored0(raw, dtype)
    return level_values(_next_grid(reconstruct(levels, n - 1), raw, dtype))


def quantise(values: np.ndarray, step: float) -> np.ndarray:
    """``round(values / step)`` as int32; raises if a value does not fit."""
    q = np.rint(values.astype(np.float64) / step)
    if q.size and (np.nanmax(np.abs(q)) > 2**31 - 2):
        raise SourceError(
            "precision {step} is too fine for values up to {top:g}: the quantised values do "
            "not fit in int32; choose a coarser {precision}.",
            params={"precision": "precision"},
            step=step,
            top=float(np.nanmax(np.abs(values))),
        )
    return q.astype(np.int32)


def dequantise(q: np.ndarray, step: float, dtype: np.dtype) -> np.ndarray:
    """Inverse of :func:`quantise`, cast to the source dtype."""
    return (q.astype(np.float64) * step).astype(dtype)
