"""Numba kernels of the residual level encodings and the nodata fill (re-exported by
:mod:`tiler._kernels_nb`, the kernel module :mod:`tiler.kernels` loads).

As there: each kernel repeats the numpy reference's (:mod:`tiler.encoding`) arithmetic
operation by operation, in the same precision and order, so results are bit-identical (the
tests check it); integer sums are exact or wrap alike, float sums keep the reference's order.
"""

from __future__ import annotations

import numpy as np

from tiler.jit import cached_njit

_FM = {"nnan", "ninf", "nsz"}  # none changes a finite value (see tiler._kernels_nb)
# nogil: a decode on a streamer's loader thread must not stall the caller's (planning) thread
_OPTS = {"fastmath": _FM, "nogil": True}
_jit = cached_njit(**_OPTS)


@_jit
def _predict_int(g, y, x, h, kind):
    """Floor prediction of vertex (y, x) from its level neighbours ``h`` apart (int64)."""
    if kind == 0:  # horizontal edge midpoint
        return (np.int64(g[y, x - h]) + np.int64(g[y, x + h])) >> 1
    if kind == 1:  # vertical edge midpoint
        return (np.int64(g[y - h, x]) + np.int64(g[y + h, x])) >> 1
    s = np.int64(g[y - h, x - h]) + np.int64(g[y - h, x + h])
    s = s + np.int64(g[y + h, x - h])
    return (s + np.int64(g[y + h, x + h])) >> 2


@_jit
def _predict_float(g, y, x, h, kind):
    """Mean prediction of vertex (y, x), in float64, in the numpy reference's order."""
    if kind == 0:
        return (np.float64(g[y, x - h]) + np.float64(g[y, x + h])) * 0.5
    if kind == 1:
        return (np.float64(g[y - h, x]) + np.float64(g[y + h, x])) * 0.5
    s = np.float64(g[y - h, x - h]) + np.float64(g[y - h, x + h])
    s = s + np.float64(g[y + h, x - h])
    return (s + np.float64(g[y + h, x + h])) * 0.25


@_jit
def fill_int(g, valid, k, fill):
    """In place: invalid vertices, coarse to fine, take the coarser level's floor prediction."""
    last = g.shape[0] - 1
    for y in (0, last):
        for x in (0, last):
            if not valid[y, x]:
                g[y, x] = fill
    for lev in range(1, k + 1):
        h = 1 << (k - lev)
        for r in range(0, (last >> (k - lev)) + 1):
            y = r * h
            if r & 1:
                for x in range(0, last + 1, 2 * h):
                    if not valid[y, x]:
                        g[y, x] = _predict_int(g, y, x, h, 1)
                    if x < last and not valid[y, x + h]:
                        g[y, x + h] = _predict_int(g, y, x + h, h, 2)
            else:
                for x in range(h, last + 1, 2 * h):
                    if not valid[y, x]:
                        g[y, x] = _predict_int(g, y, x, h, 0)


@_jit
def fill_float(g, valid, k, fill):
    """:func:`fill_int` for float grids (float64 means rounded to the grid's dtype)."""
    last = g.shape[0] - 1
    for y in (0, last):
        for x in (0, last):
            if not valid[y, x]:
                g[y, x] = fill
    for lev in range(1, k + 1):
        h = 1 << (k - lev)
        for r in range(0, (last >> (k - lev)) + 1):
            y = r * h
            if r & 1:
                for x in range(0, last + 1, 2 * h):
                    if not valid[y, x]:
                        g[y, x] = _predict_float(g, y, x, h, 1)
                    if x < last and not valid[y, x + h]:
                        g[y, x + h] = _predict_float(g, y, x + h, h, 2)
            else:
                for x in range(h, last + 1, 2 * h):
                    if not valid[y, x]:
                        g[y, x] = _predict_float(g, y, x, h, 0)


@_jit
def _zz(w, bits):
    """Zigzag of ``w`` wrapped to ``bits <= 32`` bits (two's complement), as an int64 >= 0."""
    sh = 64 - bits
    w = (w << sh) >> sh
    return ((w << 1) ^ (w >> 63)) & ((np.int64(1) << bits) - 1)


@_jit
def encode_int(g, k, bits, out):
    """Residual-encode an integer block into its sequence ``out`` (unsigned, same size)."""
    last = g.shape[0] - 1
    out[0] = _zz(np.int64(g[0, 0]), bits)
    out[1] = _zz(np.int64(g[0, last]), bits)
    out[2] = _zz(np.int64(g[last, 0]), bits)
    out[3] = _zz(np.int64(g[last, last]), bits)
    p = 4
    for lev in range(1, k + 1):
        h = 1 << (k - lev)
        for r in range(0, (last >> (k - lev)) + 1):
            y = r * h
            odd = r & 1
            x = 0 if odd else h
            while x <= last:
                kind = 0 if not odd else (1 + ((x >> (k - lev)) & 1))
                out[p] = _zz(np.int64(g[y, x]) - _predict_int(g, y, x, h, kind), bits)
                p += 1
                x += h if odd else 2 * h


@_jit
def encode_float(g, gbits, k, scratch, sbits, out):
    """float-xor encoding: value bits XOR the bits of the prediction rounded to the dtype.

    Per sample (:func:`_predict_float`): the per-level loops of :func:`decode_float` would
    compile ~5 s longer per dtype for ~0.6 ms a 1025^2 block, <1 % of ``process_block``."""
    last = g.shape[0] - 1
    out[0] = gbits[0, 0]
    out[1] = gbits[0, last]
    out[2] = gbits[last, 0]
    out[3] = gbits[last, last]
    p = 4
    for lev in range(1, k + 1):
        h = 1 << (k - lev)
        for r in range(0, (last >> (k - lev)) + 1):
            y = r * h
            odd = r & 1
            x = 0 if odd else h
            while x <= last:
                kind = 0 if not odd else (1 + ((x >> (k - lev)) & 1))
                scratch[0] = _predict_float(g, y, x, h, kind)
                out[p] = gbits[y, x] ^ sbits[0]
                p += 1
                x += h if odd else 2 * h


@_jit
def _unzz(z):
    return (z >> 1) ^ -(z & 1)


@_jit
def _decode_level(seq, p, g, h, m, mi, mj):
    """One level of :func:`decode_int` (vertices ``h`` apart, ``m`` coarse intervals per
    side) from ``seq[p:]``; returns the position after the level. Per coarse row, its edge
    midpoints, then the row below it: vertical midpoints and centres, which share the column
    sums ``g[y - h, x] + g[y + h, x]``. Only coarse rows ``0..mi`` and columns ``0..mj`` are
    decoded (the window, ``mi = mj = m`` for the whole grid); values past it are skipped. Integer
    sums are exact (or wrap alike), so the results equal :func:`_predict_int`'s, and the numpy
    reference's, bit for bit."""
    end = p + (m + 1) * m + m * (2 * m + 1)
    for i in range(mi + 1):
        row = g[i * 2 * h]
        for j in range(mj):  # horizontal edge midpoints of coarse row i
            x = (2 * j + 1) * h
            pred = (np.int64(row[x - h]) + np.int64(row[x + h])) >> 1
            row[x] = _unzz(np.int64(seq[p + j])) + pred
        p += m
        if i == mi:
            break
        a = row
        b = g[(i + 1) * 2 * h]
        c = g[(2 * i + 1) * h]
        s0 = np.int64(a[0]) + np.int64(b[0])
        for j in range(mj):  # vertical midpoint at 2jh, centre at (2j+1)h
            x = 2 * j * h
            s1 = np.int64(a[x + 2 * h]) + np.int64(b[x + 2 * h])
            c[x] = _unzz(np.int64(seq[p + 2 * j])) + (s0 >> 1)
            c[x + h] = _unzz(np.int64(seq[p + 2 * j + 1])) + ((s0 + s1) >> 2)
            s0 = s1
        c[2 * mj * h] = _unzz(np.int64(seq[p + 2 * mj])) + (s0 >> 1)
        p += 2 * m + 1
    return end


@_jit
def _window(n, h):
    """Coarse intervals (``2h`` apart) that cover grid indices ``0..n-1``."""
    return (n - 1 + 2 * h - 1) // (2 * h)


@_jit
def decode_int(seq, g, k, first, rows, cols):
    """Decode levels ``first..k`` of an integer grid ``g`` (side ``2**k+1``) in place.

    ``seq`` holds the stored values of those levels; the coarser vertices of ``g`` are set.
    Only ``g[:rows, :cols]`` is wanted: each level decodes the coarse cells that cover it
    (the rest of ``g`` is left as it was); ``rows = cols = 2**k+1`` decodes every vertex.
    """
    last = g.shape[0] - 1
    p = 0
    if first == 0:
        g[0, 0] = _unzz(np.int64(seq[0]))
        g[0, last] = _unzz(np.int64(seq[1]))
        g[last, 0] = _unzz(np.int64(seq[2]))
        g[last, last] = _unzz(np.int64(seq[3]))
        p = 4
    for lev in range(max(first, 1), k + 1):
        m = 1 << (lev - 1)
        h = 1 << (k - lev)
        mi = _window(rows, h)
        mj = _window(cols, h)
        if lev == k:  # constant strides for the two finest levels (15/16 of the values)
            p = _decode_level(seq, p, g, 1, m, mi, mj)
        elif lev == k - 1:
            p = _decode_level(seq, p, g, 2, m, mi, mj)
        else:
            p = _decode_level(seq, p, g, h, m, mi, mj)


@_jit
def _decode_level_float(seq, p, g, gbits, h, m, pred, pbits, rows, mi, mj):
    """One level of :func:`decode_float` from ``seq[p:]``; returns the position after the level.

    Per coarse row (``2h`` apart): its edge midpoints, then the row below it. A coarse row's
    vertices are copied once to a contiguous float64 row (``rows``: two, swapped), a row's
    predictions computed from those into ``pred`` (vertical/horizontal midpoints in row 0,
    centres in row 1; rounded to the dtype by the store), then XORed with the stored bits
    through ``pbits``, ``pred``'s unsigned view: branch-free contiguous loops instead of a
    per-sample :func:`_predict_float`, with its float operations in its order (the centre's
    ``((tl + tr) + bl) + br``: float sums are not associative), so bit-identical values. Only
    coarse rows ``0..mi`` and columns ``0..mj`` are decoded (``mi = mj = m``: all)."""
    end = p + (m + 1) * m + m * (2 * m + 1)
    a = rows[0]
    b = rows[1]
    pv = pred[0]
    pc = pred[1]
    bv = pbits[0]
    bc = pbits[1]
    row = g[0]
    for j in range(mj + 1):
        a[j] = np.float64(row[2 * j * h])
    for i in range(mi + 1):
        y = 2 * i * h
        for j in range(mj):
            pv[j] = (a[j] + a[j + 1]) * 0.5
        rb = gbits[y]
        for j in range(mj):
            rb[(2 * j + 1) * h] = seq[p + j] ^ bv[j]
        p += m
        if i == mi:
            break
        row = g[y + 2 * h]
        for j in range(mj + 1):
            b[j] = np.float64(row[2 * j * h])
        for j in range(mj + 1):
            pv[j] = (a[j] + b[j]) * 0.5
        for j in range(mj):
            pc[j] = (((a[j] + a[j + 1]) + b[j]) + b[j + 1]) * 0.25
        cb = gbits[y + h]
        for j in range(mj):
            cb[2 * j * h] = seq[p + 2 * j] ^ bv[j]
            cb[(2 * j + 1) * h] = seq[p + 2 * j + 1] ^ bc[j]
        cb[2 * mj * h] = seq[p + 2 * mj] ^ bv[mj]
        p += 2 * m + 1
        a, b = b, a
    return end


@_jit
def decode_float(seq, g, gbits, k, first, scratch, sbits, rows, cols):
    """:func:`decode_int` for the float-xor encoding (the same ``rows``/``cols`` window).
    ``scratch`` (the grid's dtype, ``(2, n)`` with ``n > 2**(k-1)``) and ``sbits`` (its
    unsigned view) hold one row's predictions."""
    last = g.shape[0] - 1
    p = 0
    if first == 0:
        gbits[0, 0] = seq[0]
        gbits[0, last] = seq[1]
        gbits[last, 0] = seq[2]
        gbits[last, last] = seq[3]
        p = 4
    buf = np.empty((2, (last >> 1) + 1), np.float64)
    # a constant stride for the finest level (3/4 of the values): 1025^2 float32 ~0.8x the
    # time; one for the next level too (as decode_int) compiled ~0.6 s longer for no gain
    for lev in range(max(first, 1), k + 1):
        m = 1 << (lev - 1)
        h = 1 << (k - lev)
        mi = _window(rows, h)
        mj = _window(cols, h)
        if lev == k:
            p = _decode_level_float(seq, p, g, gbits, 1, m, scratch, sbits, buf, mi, mj)
        else:
            p = _decode_level_float(seq, p, g, gbits, h, m, scratch, sbits, buf, mi, mj)
