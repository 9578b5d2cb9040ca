"""Numba kernels for the tiler's per-block hot loops (imported lazily by :mod:`tiler.kernels`).

Each kernel repeats the numpy reference's arithmetic operation by operation, in the same
precision and order, so results are bit-identical (the tests check it). No fastmath flag that
changes a finite value: only ``nnan``/``ninf``/``nsz`` (the callers pass finite grids), which
lets LLVM vectorise the max reductions without reassociating sums.
"""

from __future__ import annotations

import logging
import os
import tempfile

import numba
import numpy as np

log = logging.getLogger(__name__)

_FM = {"nnan", "ninf", "nsz"}


def _jit(fn):
    """``njit(cache=True)``; if no cache directory is writable, a per-user temp one, else none."""
    try:
        return numba.njit(cache=True, fastmath=_FM)(fn)
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        fallback = os.path.join(tempfile.gettempdir(), f"terrastream-numba-{os.getuid()}")
        try:
            os.makedirs(fallback, exist_ok=True)
            numba.config.CACHE_DIR = fallback
            return numba.njit(cache=True, fastmath=_FM)(fn)
        except (OSError, RuntimeError):
            log.warning("numba cannot cache compiled kernels (%s); compiling in memory", exc)
            return numba.njit(cache=False, fastmath=_FM)(fn)


@_jit
def bound_nodes(f, valid, k, tt, out):  # noqa: C901 - one pass, all depths
    """Node maxima of |f - level-d surface| for every depth into ``out`` (float32, flat).

    ``f``: float32 ``(side, side)``; ``tt[d, i] = float32(i / s_d)``; depth ``d`` occupies
    ``out[(4**d - 1) // 3 :][: 4**d]``. Mirrors ``static_error.bound_errors_numpy``.
    """
    side = f.shape[0]
    total = out.shape[0]
    inner = np.zeros(total, np.float32)
    top = np.zeros(total, np.float32)
    left = np.zeros(total, np.float32)
    tl = np.zeros(total, np.float32)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y in range(side - 1):
        off = 0
        for d in range(k):
            sh = k - d
            s = 1 << sh
            n = 1 << d
            i = y >> sh
            iv = y & (s - 1)
            v = tt[d, iv]
            r0 = i * s
            r1 = r0 + s
            base = off + i * n
            for j in range(n):
                x0 = j * s
                a = f[r0, x0]
                b = f[r0, x0 + s]
                c = f[r1, x0]
                dd = f[r1, x0 + s]
                ba = b - a
                ca = c - a
                q = b + c - a - dd
                vca = v * ca
                acc = zero
                for iu in range(s):
                    u = tt[d, iu]
                    g = f[y, x0 + iu] - a
                    g = g - u * ba
                    g = g - vca
                    m1 = min(u, v)
                    m2 = min(one - u - v, zero)
                    e = max(abs(g + q * m1), abs(g - q * m2))
                    if not valid[y, x0 + iu]:
                        e = zero
                    if iu == 0:
                        if e > left[base + j]:
                            left[base + j] = e
                        if iv == 0:
                            tl[base + j] = e
                    acc = max(acc, e)
                if acc > inner[base + j]:
                    inner[base + j] = acc
                if iv == 0:
                    top[base + j] = acc
            off += n * n
    # last row and column: linear interpolation along the border, then combine
    last = side - 1
    lastrow = np.empty(side, np.float32)
    lastcol = np.empty(side, np.float32)
    off = 0
    for d in range(k):
        sh = k - d
        s = 1 << sh
        n = 1 << d
        for j in range(n):
            for iu in range(s):
                t = tt[d, iu]
                x = j * s + iu
                ir = f[last, j * s] * (one - t) + f[last, j * s + s] * t
                er = abs(f[last, x] - ir)
                lastrow[x] = er if valid[last, x] else zero
                ic = f[j * s, last] * (one - t) + f[j * s + s, last] * t
                ec = abs(f[x, last] - ic)
                lastcol[x] = ec if valid[x, last] else zero
        ec = abs(f[last, last] - f[last, last])
        lastrow[last] = ec if valid[last, last] else zero
        lastcol[last] = lastrow[last]
        for i in range(n):
            for j in range(n):
                m = inner[off + i * n + j]
                if i < n - 1:
                    bot = top[off + (i + 1) * n + j]
                else:
                    bot = zero
                    for x in range(j * s, j * s + s):
                        bot = max(bot, lastrow[x])
                if j < n - 1:
                    rgt = left[off + i * n + j + 1]
                else:
                    rgt = zero
                    for yy in range(i * s, i * s + s):
                        rgt = max(rgt, lastcol[yy])
                if j == n - 1:
                    cor = lastcol[(i + 1) * s]
                elif i == n - 1:
                    cor = lastrow[(j + 1) * s]
                else:
                    cor = tl[off + (i + 1) * n + j + 1]
                out[off + i * n + j] = max(max(m, bot), max(rgt, cor))
        off += n * n


@_jit
def qiu_nodes(g, valid, k, out):
    """Qiu's H for every node of every depth into ``out`` (float64, flat, depth by depth)."""
    off = 0
    for d in range(k):
        n = 1 << d
        s = 1 << (k - d)
        h = s >> 1
        for i in range(n):
            r0 = i * s
            r1 = r0 + s
            rm = r0 + h
            for j in range(n):
                c0 = j * s
                c1 = c0 + s
                cm = c0 + h
                a = np.float64(g[r0, c0])
                b = np.float64(g[r0, c1])
                c = np.float64(g[r1, c0])
                dd = np.float64(g[r1, c1])
                e = 0.0
                if valid[r0, cm]:
                    e = max(e, abs(np.float64(g[r0, cm]) - (a + b) * 0.5))
                if valid[r1, cm]:
                    e = max(e, abs(np.float64(g[r1, cm]) - (c + dd) * 0.5))
                if valid[rm, c0]:
                    e = max(e, abs(np.float64(g[rm, c0]) - (a + c) * 0.5))
                if valid[rm, c1]:
                    e = max(e, abs(np.float64(g[rm, c1]) - (b + dd) * 0.5))
                if valid[rm, cm]:
                    ctr = np.float64(g[rm, cm])
                    e = max(e, max(abs(ctr - (a + dd) * 0.5), abs(ctr - (b + c) * 0.5)))
                out[off + i * n + j] = e
        off += n * n


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
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            for x in range(0, last + 1, h):
                odd_c = (x // h) & 1
                if (odd_r or odd_c) and not valid[y, x]:
                    kind = 0 if not odd_r else (1 if not odd_c else 2)
                    g[y, x] = _predict_int(g, y, x, h, kind)


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
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            for x in range(0, last + 1, h):
                odd_c = (x // h) & 1
                if (odd_r or odd_c) and not valid[y, x]:
                    kind = 0 if not odd_r else (1 if not odd_c else 2)
                    g[y, x] = _predict_float(g, y, x, h, kind)


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
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            x0 = 0 if odd_r else h
            step = h if odd_r else 2 * h
            for x in range(x0, last + 1, step):
                odd_c = (x // h) & 1
                kind = 0 if not odd_r else (1 if not odd_c else 2)
                out[p] = _zz(np.int64(g[y, x]) - _predict_int(g, y, x, h, kind), bits)
                p += 1


@_jit
def encode_float(g, gbits, k, scratch, sbits, out):
    """float-xor encoding: value bits XOR the bits of the prediction rounded to the dtype."""
    last = g.shape[0] - 1
    out[0] = gbits[0, 0]
    out[1] = gbits[0, last]
    out[2] = gbits[last, 0]
    out[3] = gbits[last, last]
    p = 4
    for lev in range(1, k + 1):
        h = 1 << (k - lev)
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            x0 = 0 if odd_r else h
            step = h if odd_r else 2 * h
            for x in range(x0, last + 1, step):
                odd_c = (x // h) & 1
                kind = 0 if not odd_r else (1 if not odd_c else 2)
                scratch[0] = _predict_float(g, y, x, h, kind)
                out[p] = gbits[y, x] ^ sbits[0]
                p += 1


@_jit
def _unzz(z):
    return (z >> 1) ^ -(z & 1)


@_jit
def decode_int(seq, g, k, first):
    """Decode levels ``first..k`` of an integer grid ``g`` (side ``2**k+1``) in place.

    ``seq`` holds the stored values of those levels; the coarser vertices of ``g`` are set.
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
        h = 1 << (k - lev)
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            x0 = 0 if odd_r else h
            step = h if odd_r else 2 * h
            for x in range(x0, last + 1, step):
                odd_c = (x // h) & 1
                kind = 0 if not odd_r else (1 if not odd_c else 2)
                g[y, x] = _unzz(np.int64(seq[p])) + _predict_int(g, y, x, h, kind)
                p += 1


@_jit
def decode_float(seq, g, gbits, k, first, scratch, sbits):
    """:func:`decode_int` for the float-xor encoding."""
    last = g.shape[0] - 1
    p = 0
    if first == 0:
        gbits[0, 0] = seq[0]
        gbits[0, last] = seq[1]
        gbits[last, 0] = seq[2]
        gbits[last, last] = seq[3]
        p = 4
    for lev in range(max(first, 1), k + 1):
        h = 1 << (k - lev)
        for y in range(0, last + 1, h):
            odd_r = (y // h) & 1
            x0 = 0 if odd_r else h
            step = h if odd_r else 2 * h
            for x in range(x0, last + 1, step):
                odd_c = (x // h) & 1
                kind = 0 if not odd_r else (1 if not odd_c else 2)
                scratch[0] = _predict_float(g, y, x, h, kind)
                gbits[y, x] = seq[p] ^ sbits[0]
                p += 1
