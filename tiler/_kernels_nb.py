"""Numba kernels for the tiler's per-block hot loops (imported lazily by :mod:`tiler.kernels`).

Each kernel repeats the numpy reference's arithmetic operation by operation, in the same
precision and order, so results are bit-identical (the tests check it). No fastmath flag that
changes a finite value: only ``nnan``/``ninf``/``nsz`` (the callers pass finite grids), which
lets LLVM vectorise the max reductions without reassociating sums.
"""

from __future__ import annotations

import numpy as np

from tiler.jit import cached_njit

_FM = {"nnan", "ninf", "nsz"}
# nogil: a decode on a streamer's loader thread must not stall the caller's (planning) thread
_OPTS = {"fastmath": _FM, "nogil": True}


_jit = cached_njit(**_OPTS)


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
def _encode_level_float(g, gbits, h, m, pred, pbits, rows, out, p):
    """One level of :func:`encode_float` into ``out[p:]``, with :func:`_decode_level_float`'s
    loops; returns the position after it."""
    a = rows[0]
    b = rows[1]
    pv = pred[0]
    pc = pred[1]
    bv = pbits[0]
    bc = pbits[1]
    row = g[0]
    for j in range(m + 1):
        a[j] = np.float64(row[2 * j * h])
    for i in range(m + 1):
        y = 2 * i * h
        for j in range(m):
            pv[j] = (a[j] + a[j + 1]) * 0.5
        rb = gbits[y]
        for j in range(m):
            out[p + j] = rb[(2 * j + 1) * h] ^ bv[j]
        p += m
        if i == m:
            break
        row = g[y + 2 * h]
        for j in range(m + 1):
            b[j] = np.float64(row[2 * j * h])
        for j in range(m + 1):
            pv[j] = (a[j] + b[j]) * 0.5
        for j in range(m):
            pc[j] = (((a[j] + a[j + 1]) + b[j]) + b[j + 1]) * 0.25
        cb = gbits[y + h]
        for j in range(m):
            out[p + 2 * j] = cb[2 * j * h] ^ bv[j]
            out[p + 2 * j + 1] = cb[(2 * j + 1) * h] ^ bc[j]
        out[p + 2 * m] = cb[2 * m * h] ^ bv[m]
        p += 2 * m + 1
        a, b = b, a
    return p


@_jit
def encode_float(g, gbits, k, scratch, sbits, out):
    """float-xor encoding: value bits XOR the bits of the prediction rounded to the dtype.

    ``scratch`` (the grid's dtype, at least ``2**k+1`` long) and ``sbits`` (its unsigned
    view) hold one row's predictions."""
    last = g.shape[0] - 1
    out[0] = gbits[0, 0]
    out[1] = gbits[0, last]
    out[2] = gbits[last, 0]
    out[3] = gbits[last, last]
    p = 4
    rows = np.empty((2, (last >> 1) + 1), np.float64)
    for lev in range(1, k + 1):
        m = 1 << (lev - 1)
        if lev == k:  # constant strides for the two finest levels, as in decode_int
            p = _encode_level_float(g, gbits, 1, m, scratch, sbits, rows, out, p)
        elif lev == k - 1:
            p = _encode_level_float(g, gbits, 2, m, scratch, sbits, rows, out, p)
        else:
            p = _encode_level_float(g, gbits, 1 << (k - lev), m, scratch, sbits, rows, out, p)


@_jit
def _unzz(z):
    return (z >> 1) ^ -(z & 1)


@_jit
def _decode_level(seq, p, g, h, m):
    """One level of :func:`decode_int` (vertices ``h`` apart, ``m`` coarse intervals per
    side) from ``seq[p:]``; returns the position after it. Per coarse row, its edge midpoints,
    then the row below it: vertical midpoints and centres, which share the column sums
    ``g[y - h, x] + g[y + h, x]``. Integer sums are exact (or wrap alike), so the results
    equal :func:`_predict_int`'s, and the numpy reference's, bit for bit."""
    last = 2 * m * h
    for i in range(m + 1):
        row = g[i * 2 * h]
        for j in range(m):  # horizontal edge midpoints of coarse row i
            x = (2 * j + 1) * h
            pred = (np.int64(row[x - h]) + np.int64(row[x + h])) >> 1
            row[x] = _unzz(np.int64(seq[p + j])) + pred
        p += m
        if i == m:
            break
        a = row
        b = g[(i + 1) * 2 * h]
        c = g[(2 * i + 1) * h]
        s0 = np.int64(a[0]) + np.int64(b[0])
        for j in range(m):  # vertical midpoint at 2jh, centre at (2j+1)h
            x = 2 * j * h
            s1 = np.int64(a[x + 2 * h]) + np.int64(b[x + 2 * h])
            c[x] = _unzz(np.int64(seq[p + 2 * j])) + (s0 >> 1)
            c[x + h] = _unzz(np.int64(seq[p + 2 * j + 1])) + ((s0 + s1) >> 2)
            s0 = s1
        c[last] = _unzz(np.int64(seq[p + 2 * m])) + (s0 >> 1)
        p += 2 * m + 1
    return p


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
        m = 1 << (lev - 1)
        if lev == k:  # constant strides for the two finest levels (15/16 of the values)
            p = _decode_level(seq, p, g, 1, m)
        elif lev == k - 1:
            p = _decode_level(seq, p, g, 2, m)
        else:
            p = _decode_level(seq, p, g, 1 << (k - lev), m)


@_jit
def _decode_level_float(seq, p, g, gbits, h, m, pred, pbits, rows):
    """One level of :func:`decode_float` from ``seq[p:]``; returns the position after it.

    Per coarse row (``2h`` apart): its edge midpoints, then the row below it. A coarse row's
    vertices are copied once to a contiguous float64 row (``rows``: two, swapped), a row's
    predictions computed from those into ``pred`` (vertical/horizontal midpoints in row 0,
    centres in row 1; rounded to the dtype by the store), then XORed with the stored bits
    through ``pbits``, ``pred``'s unsigned view: branch-free contiguous loops instead of a
    per-sample :func:`_predict_float`, with its float operations in its order (the centre's
    ``((tl + tr) + bl) + br``: float sums are not associative), so bit-identical values."""
    a = rows[0]
    b = rows[1]
    pv = pred[0]
    pc = pred[1]
    bv = pbits[0]
    bc = pbits[1]
    row = g[0]
    for j in range(m + 1):
        a[j] = np.float64(row[2 * j * h])
    for i in range(m + 1):
        y = 2 * i * h
        for j in range(m):
            pv[j] = (a[j] + a[j + 1]) * 0.5
        rb = gbits[y]
        for j in range(m):
            rb[(2 * j + 1) * h] = seq[p + j] ^ bv[j]
        p += m
        if i == m:
            break
        row = g[y + 2 * h]
        for j in range(m + 1):
            b[j] = np.float64(row[2 * j * h])
        for j in range(m + 1):
            pv[j] = (a[j] + b[j]) * 0.5
        for j in range(m):
            pc[j] = (((a[j] + a[j + 1]) + b[j]) + b[j + 1]) * 0.25
        cb = gbits[y + h]
        for j in range(m):
            cb[2 * j * h] = seq[p + 2 * j] ^ bv[j]
            cb[(2 * j + 1) * h] = seq[p + 2 * j + 1] ^ bc[j]
        cb[2 * m * h] = seq[p + 2 * m] ^ bv[m]
        p += 2 * m + 1
        a, b = b, a
    return p


@_jit
def decode_float(seq, g, gbits, k, first, scratch, sbits):
    """:func:`decode_int` for the float-xor encoding (``scratch``/``sbits``: as in
    :func:`encode_float`, one row's predictions)."""
    last = g.shape[0] - 1
    p = 0
    if first == 0:
        gbits[0, 0] = seq[0]
        gbits[0, last] = seq[1]
        gbits[last, 0] = seq[2]
        gbits[last, last] = seq[3]
        p = 4
    rows = np.empty((2, (last >> 1) + 1), np.float64)
    for lev in range(max(first, 1), k + 1):
        m = 1 << (lev - 1)
        if lev == k:  # constant strides for the two finest levels (15/16 of the values)
            p = _decode_level_float(seq, p, g, gbits, 1, m, scratch, sbits, rows)
        elif lev == k - 1:
            p = _decode_level_float(seq, p, g, gbits, 2, m, scratch, sbits, rows)
        else:
            p = _decode_level_float(seq, p, g, gbits, 1 << (k - lev), m, scratch, sbits, rows)


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
