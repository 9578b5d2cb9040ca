"""Numba kernels for the tiler's per-block hot loops (imported lazily by :mod:`tiler.kernels`).

Each kernel repeats the numpy reference's arithmetic operation by operation, in the same
precision and order, so results are bit-identical (the tests check it). No fastmath flag that
changes a finite value: only ``nnan``/``ninf``/``nsz`` (the callers pass finite grids), which
lets LLVM vectorise the max reductions without reassociating sums.
"""

from __future__ import annotations

import numpy as np

from tiler._codec_nb import (  # _jit: one set of njit options (fastmath flags, nogil)
    _jit,
    decode_float,
    decode_int,
    encode_float,
    encode_int,
    fill_float,
    fill_int,
)

__all__ = [  # the residual encodings and the nodata fill are in tiler._codec_nb
    "bound_nodes",
    "decode_float",
    "decode_int",
    "encode_float",
    "encode_int",
    "fill_float",
    "fill_int",
    "monotone_pack",
    "qiu_nodes",
    "recentre",
]


@_jit
def bound_nodes(f, valid, k, tt, out):
    """Node maxima of |f - level-d surface| for every depth into ``out`` (float32, flat).

    ``f``: float32 ``(side, side)``; ``tt[d, i] = float32(i / s_d)``; depth ``d`` occupies
    ``out[(4**d - 1) // 3 :][: 4**d]``. Mirrors ``static_error.bound_errors_numpy``.

    One pass over the rows for all depths: per depth, the node-row's corners are expanded to
    per-column arrays when a node row starts, so the per-sample loop is branch-free over the
    whole row (vectorised), keeping a running column max ``run`` that is reduced per node when
    the node row ends (its first row gives the top edges, its first column the left ones).
    """
    side = f.shape[0]
    w = side - 1
    total = out.shape[0]
    inner = np.zeros(total, np.float32)
    top = np.zeros(total, np.float32)
    left = np.zeros(total, np.float32)
    tl = np.zeros(total, np.float32)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    uu = np.zeros((k, w), np.float32)  # u of each column, per depth
    omu = np.zeros((k, w), np.float32)  # 1 - u
    aa = np.zeros((k, w), np.float32)
    ba = np.zeros((k, w), np.float32)
    ca = np.zeros((k, w), np.float32)
    qq = np.zeros((k, w), np.float32)
    run = np.zeros((k, w), np.float32)
    for d in range(k):
        s = 1 << (k - d)
        for x in range(w):
            uu[d, x] = tt[d, x & (s - 1)]
            omu[d, x] = one - uu[d, x]
    for y in range(w):
        off = 0
        for d in range(k):
            sh = k - d
            s = 1 << sh
            n = 1 << d
            i = y >> sh
            iv = y & (s - 1)
            v = tt[d, iv]
            base = off + i * n
            ud, od, ad, bd, cd, qd, rd = uu[d], omu[d], aa[d], ba[d], ca[d], qq[d], run[d]
            if iv == 0:  # flat loops: vector stores (scalar ones stall the vector loads)
                fa = f[i * s]
                fc = f[i * s + s]
                msk = ~(s - 1)
                for x in range(w):
                    x0 = x & msk
                    a = fa[x0]
                    b = fa[x0 + s]
                    c = fc[x0]
                    dd = fc[x0 + s]
                    ad[x] = a
                    bd[x] = b - a
                    cd[x] = c - a
                    qd[x] = b + c - a - dd
                for x in range(w):
                    rd[x] = zero
            fy = f[y]
            vy = valid[y]
            for x in range(w):
                u = ud[x]
                g = fy[x] - ad[x]
                g = g - u * bd[x]
                g = g - v * cd[x]
                m1 = u if u < v else v
                t = od[x] - v
                m2 = t if t < zero else zero
                e1 = abs(g + qd[x] * m1)
                e2 = abs(g - qd[x] * m2)
                e = e1 if e1 > e2 else e2
                e = e if vy[x] else zero
                rd[x] = rd[x] if rd[x] > e else e
            if iv == 0:
                for j in range(n):
                    m = zero
                    for x in range(j * s, j * s + s):
                        m = max(m, rd[x])
                    top[base + j] = m
                    tl[base + j] = rd[j * s]
            if iv == s - 1:
                for j in range(n):
                    m = zero
                    for x in range(j * s, j * s + s):
                        m = max(m, rd[x])
                    inner[base + j] = m
                    left[base + j] = rd[j * s]
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
def recentre(g, ref, out):
    """``out = float32(float64(g) - ref)``; returns ``max |float64(g) - ref|``."""
    span = 0.0
    for y in range(g.shape[0]):
        for x in range(g.shape[1]):
            dv = np.float64(g[y, x]) - ref
            out[y, x] = dv
            a = abs(dv)
            if a > span:
                span = a
    return span


@_jit
def monotone_pack(flat, k, cap, mult, out):
    """Qiu's Eq. 3 in place on a depth-packed field, then ``value * mult`` packed as
    ``static_error.pack_field`` does (tile maxima beyond ``cap``) into ``out`` (float64)."""
    offs = np.zeros(k + 1, np.int64)
    for d in range(k):
        offs[d + 1] = offs[d] + (1 << (2 * d))
    for d in range(k - 1, 0, -1):
        n = 1 << d
        m = n >> 1
        co = offs[d]
        po = offs[d - 1]
        for i in range(m):
            r0 = co + 2 * i * n
            r1 = r0 + n
            for j in range(m):
                c = max(
                    max(flat[r0 + 2 * j], flat[r0 + 2 * j + 1]),
                    max(flat[r1 + 2 * j], flat[r1 + 2 * j + 1]),
                )
                if c > flat[po + i * m + j]:
                    flat[po + i * m + j] = c
    p = 0
    for d in range(k):
        n = 1 << d
        if d <= cap:
            for idx in range(n * n):
                out[p + idx] = flat[offs[d] + idx] * mult
            p += n * n
        else:
            nc = 1 << cap
            r = n >> cap
            for ci in range(nc):
                for cj in range(nc):
                    m = flat[offs[d] + ci * r * n + cj * r] * mult
                    for yy in range(ci * r, ci * r + r):
                        for xx in range(cj * r, cj * r + r):
                            m = max(m, flat[offs[d] + yy * n + xx] * mult)
                    out[p + ci * nc + cj] = m
            p += nc * nc
