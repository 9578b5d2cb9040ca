"""Numba kernels of the snapped-edge check in :mod:`render.stitch_fast`: the gathers of
patches' vertex heights and cell bounds from :meth:`render.node_boxes.NodeBoxes.flat` (the
values :meth:`~render.node_boxes.NodeBoxes.vertex_heights` and
:meth:`~render.node_boxes.NodeBoxes.cell_bounds` give) and, per strip, the rest of
:func:`render.snap_error.snap_excess` after its matrix product (maxima over each triangle's
points, the masked patches' looser bound, the cells' bound added, the strip's maximum): the
reference's float operations on the same values (no fastmath), so the same bits (tested)."""

from __future__ import annotations

import math

import numpy as np

from tiler.jit import cached_njit

_jit = cached_njit(nogil=True, error_model="numpy")


@_jit
def gather_heights(buf, off, side, lev, b, d, r, c, lv, n):
    """``(m, (n+1)**2)`` level-``lv`` vertex heights ``[row j, column i]`` (flat) of patches
    ``(b, d, r, c)`` of ``n`` cells each, from the blocks' level-``lev`` grids in ``buf``."""
    m = b.shape[0]
    w = n + 1
    out = np.empty((m, w * w))
    for a in range(m):
        bb = b[a]
        o, s, rr = off[bb, 0], side[bb, 0], lev[bb]
        span = np.int64(1) << (rr - d[a])
        step = np.int64(1) << (rr - lv[a])
        r0, c0 = r[a] * span, c[a] * span
        for j in range(w):
            base = o + (r0 + j * step) * s + c0
            for i in range(w):
                out[a, j * w + i] = buf[base + i * step]
    return out


@_jit
def gather_cells(buf, off, side, b, r, c, lv, n, k):
    """``(m, n*n)`` stored ``bound`` of each level-``lv`` cell of patches ``(b, r, c)`` of
    ``n`` cells (0 at full resolution; a field stored coarser than the level: its tile's)."""
    m = b.shape[0]
    out = np.zeros((m, n * n))
    for a in range(m):
        v = lv[a]
        if v >= k:
            continue
        bb = b[a]
        o, s = off[bb, 1 + v], side[bb, 1 + v]
        rep = (np.int64(1) << v) // s
        for j in range(n):
            base = o + ((r[a] * n + j) // rep) * s
            for i in range(n):
                out[a, j * n + i] = buf[base + (c[a] * n + i) // rep]
    return out


@_jit
def gather_patches(buf, off, side, lev, b, d, r, c, lv, n, k):
    """:func:`gather_heights` (``h``), the same with masked patches' heights zeroed (``h0``),
    which patches are masked (a NaN height) and :func:`gather_cells` (``cb``)."""
    h = gather_heights(buf, off, side, lev, b, d, r, c, lv, n)
    h0 = h.copy()
    m = h.shape[0]
    masked = np.zeros(m, np.bool_)
    for a in range(m):
        for q in range(h.shape[1]):
            if math.isnan(h[a, q]):
                masked[a] = True
                break
        if masked[a]:
            h0[a, :] = 0.0
    return h, h0, masked, gather_cells(buf, off, side, b, r, c, lv, n, k)


@_jit
def _max(a, b):
    """``np.maximum`` of two floats (NaN if either is NaN)."""
    if math.isnan(a) or a >= b:
        return a
    return b


@_jit
def strip_max(dm, starts, box, tj, ti, h, masked, cb, n, with_cb):
    """Per patch the largest triangle bound of one strip (:func:`render.snap_error.snap_excess`
    after ``dm = |W @ h|``): each triangle's largest ``dm`` over its points (``starts``), or
    for a masked patch ``max(max_box S - min_T h, max_T h - min_box S)`` (0 if not finite),
    plus (``with_cb``) the largest bound of the cells of its box ``(j0, j1, i0, i1)``."""
    m = dm.shape[0]
    nt = starts.shape[0]
    npts = dm.shape[1]
    w = n + 1
    out = np.empty(m)
    for a in range(m):
        best = 0.0
        for u in range(nt):
            s0 = starts[u]
            s1 = starts[u + 1] if u + 1 < nt else npts
            v = dm[a, s0]
            for q in range(s0 + 1, s1):
                v = _max(v, dm[a, q])
            j0, j1, i0, i1 = box[u, 0], box[u, 1], box[u, 2], box[u, 3]
            if masked[a]:
                lo_t = math.nan
                hi_t = math.nan
                for q in range(3):
                    x = h[a, tj[u, q] * w + ti[u, q]]
                    lo_t = np.fmin(lo_t, x)
                    hi_t = np.fmax(hi_t, x)
                lo_b = math.nan
                hi_b = math.nan
                for jj in range(j0, j1 + 1):
                    for ii in range(i0, i1 + 1):
                        x = h[a, jj * w + ii]
                        lo_b = np.fmin(lo_b, x)
                        hi_b = np.fmax(hi_b, x)
                e_t = np.fmax(hi_b - lo_t, hi_t - lo_b)
                v = e_t if math.isfinite(e_t) else 0.0
            if with_cb:
                cm = cb[a, j0 * n + i0]
                for jj in range(j0, j1):
                    for ii in range(i0, i1):
                        cm = _max(cm, cb[a, jj * n + ii])
                v = v + cm
            best = v if u == 0 else _max(best, v)
        out[a] = best
    return out


@_jit
def exact_all(buf, off, side, b, d, r, c, lo, hi, at_j, at_i, cor_j, cor_i, wts, k):
    """Per patch ``(b, d, r, c)`` of a block held at full resolution (level ``k``) and edge
    the largest ``|h - I|`` over the strip's samples (:func:`render.snap_error.snap_exact`):
    edge ``e`` of patch ``a`` takes the samples ``lo[a, e]:hi[a, e]`` of the templates (sample
    ``q`` at window row/column ``(at_j, at_i)[q]``, its triangle's corners at
    ``(cor_j, cor_i)[q]`` with weights ``wts[q]``); NaN samples ignored, 0 if none is finite
    or ``lo < 0`` (an edge without moved triangles)."""
    m = b.shape[0]
    out = np.zeros((m, 4))
    for a in range(m):
        bb = b[a]
        o, s = off[bb, 0], side[bb, 0]
        span = np.int64(1) << (k - d[a])
        base = o + r[a] * span * s + c[a] * span
        for e in range(4):
            if lo[a, e] < 0:
                continue
            worst = math.nan
            for q in range(lo[a, e], hi[a, e]):
                hq = buf[base + at_j[q] * s + at_i[q]]
                h0 = buf[base + cor_j[q, 0] * s + cor_i[q, 0]]
                h1 = buf[base + cor_j[q, 1] * s + cor_i[q, 1]]
                h2 = buf[base + cor_j[q, 2] * s + cor_i[q, 2]]
                interp = (h0 * wts[q, 0] + h1 * wts[q, 1]) + h2 * wts[q, 2]
                worst = np.fmax(worst, abs(hq - interp))
            out[a, e] = worst if math.isfinite(worst) else 0.0
    return out
