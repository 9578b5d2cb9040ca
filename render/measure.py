"""Measuring what a LOD frame costs in accuracy (pure numpy, no GL).

* :func:`lod_surface` evaluates the drawn (LOD) surface at every full-resolution sample of each
  patch: the patch's level grid triangulated as on the GPU (:mod:`render.mesh`), with edge
  snapping applied (snapped edge strips are rasterised triangle by triangle on the sample lattice).
* :func:`screen_errors` projects each sample's true position and the LOD surface at the same
  ``(x, y)`` with :meth:`Camera.project` and returns the pixel distances of samples in view.
* :func:`psnr`, :func:`changed_share`, :func:`crack_pixels` compare images.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from render.mesh import edge_strip_triangles, snapped_triangles
from render.select import Patches
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.store import TerrainStore

CHUNK = 1 << 21  # samples evaluated at once


@dataclass(frozen=True)
class ErrorStats:
    """Measured screen-space error of a frame (pixels) over ``samples`` samples in view."""

    max_px: float
    p99_px: float
    mean_px: float
    samples: int


def _cell_heights(full, ra, ca, s, fu, fv, upper):
    """Height at ``(fu, fv)`` of the cell with corner ``a`` at ``(ra, ca)``: its upper
    ``(a, b, d)`` or lower ``(a, c, d)`` triangle, NaN if one of that triangle's corners is
    masked (a triangle with a nodata corner is not drawn)."""
    ha = full[ra, ca]
    hb = full[ra, ca + s]
    hc = full[ra + s, ca]
    hd = full[ra + s, ca + s]
    return np.where(
        upper, ha + fu * (hb - ha) + fv * (hd - hb), ha + fv * (hc - ha) + fu * (hd - hc)
    )


def _tri_heights(
    full: np.ndarray,
    r0: int,
    c0: int,
    s: int,
    u: np.ndarray,
    v: np.ndarray,
    n: int,
    strips: tuple[np.ndarray, ...] | None = None,
):
    """Height of the regular (unsnapped) patch surface at patch cell coords ``(u, v)``: in the
    cell and triangle the point falls in, or, where that triangle is not drawn (a masked
    corner), in another drawn triangle of the patch that contains the point (it lies on their
    shared edge or corner; the surface is continuous there); NaN where none is drawn.
    ``strips``: per patch whether its N, E, S, W edge is snapped (broadcast like ``r0``): the
    cells along a snapped edge are drawn as snapped strips (:func:`lod_surface` rasterises
    them), so neither the point's cell nor a neighbour that is such a cell counts here."""
    ci = np.minimum(np.floor(u).astype(np.int64), n - 1)
    cj = np.minimum(np.floor(v).astype(np.int64), n - 1)
    fu, fv = u - ci, v - cj
    h = _cell_heights(full, r0 + cj * s, c0 + ci * s, s, fu, fv, fu >= fv)
    if strips is not None:
        h = np.where(_in_strip(strips, ci, cj, n), np.nan, h)
    miss = np.isnan(h)
    if not miss.any():
        return h
    # the points on a triangle's border: the cell's other triangle (the diagonal), the cells to
    # the left and above (the cell's left and top edges) and above-left (its corner a)
    shape = h.shape
    ci, cj, fu, fv = (np.broadcast_to(a, shape)[miss] for a in (ci, cj, fu, fv))
    r0, c0 = (np.broadcast_to(a, shape)[miss] for a in (r0, c0))
    if strips is not None:
        strips = tuple(np.broadcast_to(t, shape)[miss] for t in strips)
    got = np.full(ci.shape, np.nan)
    one = np.ones_like(fu)
    for di, dj, gu, gv, upper, on in (
        (0, 0, fu, fv, False, fu == fv),
        (1, 0, one, fv, True, fu == 0),
        (1, 0, one, fv, False, (fu == 0) & (fv == 1)),
        (0, 1, fu, one, False, fv == 0),
        (0, 1, fu, one, True, (fv == 0) & (fu == 1)),
        (1, 1, one, one, True, (fu == 0) & (fv == 0)),
        (1, 1, one, one, False, (fu == 0) & (fv == 0)),
    ):
        ok = on & (ci >= di) & (cj >= dj) & np.isnan(got)
        if strips is not None:
            ok &= ~_in_strip(strips, ci - di, cj - dj, n)
        if ok.any():
            ra, ca = r0[ok] + (cj[ok] - dj) * s, c0[ok] + (ci[ok] - di) * s
            got[ok] = _cell_heights(full, ra, ca, s, gu[ok], gv[ok], upper)
    h = h.copy() if not h.flags.writeable else h
    h[miss] = got
    return h


def _in_strip(strips: tuple[np.ndarray, ...], ci: np.ndarray, cj: np.ndarray, n: int):
    """Cell ``(ci, cj)`` lies along a snapped edge (``strips``: N, E, S, W snapped)."""
    sn, se, ss, sw = strips
    return (sn & (cj == 0)) | (se & (ci == n - 1)) | (ss & (cj == n - 1)) | (sw & (ci == 0))


def rasterise(tri: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer lattice points ``(rows, cols)`` covered (edges included) by triangles ``tri``
    ``(m, 3, 2)`` given as ``(col, row)`` ints, and the linear interpolant of ``h`` ``(m, 3)``
    (zero-area triangles are skipped)."""
    out_r, out_c, out_h = [], [], []
    t64 = np.asarray(tri, dtype=np.int64)
    e1, e2 = t64[:, 1] - t64[:, 0], t64[:, 2] - t64[:, 0]
    solid = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] != 0  # zero-area triangles cover nothing
    tri, h = t64[solid], np.asarray(h)[solid]
    lo = tri.min(axis=1)
    ext = tri.max(axis=1) - lo
    keys, inv = np.unique(ext, axis=0, return_inverse=True)
    for g, (w, hgt) in enumerate(keys):
        sel = np.flatnonzero(inv.ravel() == g)
        oy, ox = np.mgrid[0 : hgt + 1, 0 : w + 1]
        ox, oy = ox.ravel(), oy.ravel()
        for part in np.array_split(sel, max(1, len(sel) * len(ox) // CHUNK + 1)):
            t = tri[part]
            px = lo[part, 0][:, None] + ox
            py = lo[part, 1][:, None] + oy
            (x0, y0), (x1, y1), (x2, y2) = (
                (t[:, i, 0][:, None], t[:, i, 1][:, None]) for i in range(3)
            )
            area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
            w0 = (x1 - px) * (y2 - py) - (y1 - py) * (x2 - px)
            w1 = (x2 - px) * (y0 - py) - (y2 - py) * (x0 - px)
            w2 = area - w0 - w1
            sign = np.sign(area)
            inside = (w0 * sign >= 0) & (w1 * sign >= 0) & (w2 * sign >= 0)
            hh = h[part]
            val = (w0 * hh[:, 0:1] + w1 * hh[:, 1:2] + w2 * hh[:, 2:3]) / area
            out_r.append(py[inside])
            out_c.append(px[inside])
            out_h.append(val[inside])
    if not out_r:
        z = np.zeros(0, dtype=np.int64)
        return z, z, np.zeros(0)
    return np.concatenate(out_r), np.concatenate(out_c), np.concatenate(out_h)


def lod_surface(
    patches: Patches, k: int, heights: Callable[[int], np.ndarray]
) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Yield ``(block index, rows, cols, lod height)`` chunks covering every patch's samples.

    ``heights(i)`` is the full-resolution ``(2**k+1)**2`` float64 grid of ``patches.blocks[i]``
    with NaN at masked samples (NaN propagates: hidden triangles give NaN).
    """
    cells = patches.cells_log2
    spacing_log2 = k - patches.level
    snapped = patches.snap.max(axis=1) > 0
    key = np.stack([patches.block, cells, spacing_log2], 1)
    for grp in np.unique(key, axis=0):
        b, c, sl = (int(v) for v in grp)
        full = heights(b)
        sel = np.flatnonzero((key == grp).all(axis=1))
        n, s = 1 << c, 1 << sl
        e = n * s
        loc = np.arange(e + 1)
        per = (e + 1) ** 2
        for part in np.array_split(sel, max(1, len(sel) * per // CHUNK + 1)):
            r0 = patches.row[part] * e
            c0 = patches.col[part] * e
            rr, cc = np.broadcast_arrays(
                r0[:, None, None] + loc[None, :, None], c0[:, None, None] + loc[None, None, :]
            )
            v = np.broadcast_to(loc[None, :, None] / s, rr.shape)
            u = np.broadcast_to(loc[None, None, :] / s, rr.shape)
            strips = tuple((patches.snap[part, e] > 0)[:, None, None] for e in range(4))
            hreg = _reg(full, r0, c0, s, u, v, n, strips)
            # samples strictly inside the cells along a snapped edge are the strips' alone; those
            # on the strips' inner border are also the regular cells' (a strip facing nodata has
            # every triangle undrawn there, and the regular cell beside it draws them)
            sn, se, ss, sw = strips
            excl = (sn & (v < 1)) | (ss & (v > n - 1)) | (sw & (u < 1)) | (se & (u > n - 1))
            keep = ~excl
            yield b, rr[keep], cc[keep], hreg[keep]
        for i in sel[snapped[sel]]:
            tri = edge_strip_triangles(c, tuple(int(t) for t in patches.snap[i]))
            if not len(tri):
                continue
            r0, c0 = int(patches.row[i]) * e, int(patches.col[i]) * e
            tc = c0 + tri[..., 0] * s
            tr = r0 + tri[..., 1] * s
            hv = full[tr, tc]
            rows, cols, hh = rasterise(np.stack([tc, tr], -1), hv)
            yield b, rows, cols, hh


def patch_triangles(
    patches: Patches, grid: BlockGrid, heights: Callable[[int], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The CPU twin of the drawn patch mesh: every non-degenerate snapped triangle's global
    ``(col, row)`` corners ``(m, 3, 2)`` int64 and heights ``(m, 3)`` (NaN where masked)."""
    k, step = grid.k, grid.step
    if not len(patches):
        return np.zeros((0, 3, 2), np.int64), np.zeros((0, 3))
    cells = patches.cells_log2
    key = np.concatenate([cells[:, None], k - patches.level[:, None], patches.snap], 1)
    tris, hs = [], []
    for grp in np.unique(key, axis=0):
        c, sl = int(grp[0]), int(grp[1])
        sel = np.flatnonzero((key == grp).all(axis=1))
        local = snapped_triangles(c, tuple(int(t) for t in grp[2:]))  # (t, 3, 2) (i, j)
        if not len(local):
            continue
        s, e = 1 << sl, (1 << c) << sl
        blk = patches.blocks[patches.block[sel]]
        c0 = patches.col[sel] * e
        r0 = patches.row[sel] * e
        lc = c0[:, None, None] + local[None, :, :, 0] * s  # in-block (col, row)
        lr = r0[:, None, None] + local[None, :, :, 1] * s
        h = np.empty(lc.shape)
        for b in np.unique(patches.block[sel]).tolist():
            m = patches.block[sel] == b
            h[m] = heights(b)[lr[m], lc[m]]
        gc = blk[:, 1, None, None] * step + lc
        gr = blk[:, 0, None, None] * step + lr
        tris.append(np.stack([gc, gr], -1).reshape(-1, 3, 2))
        hs.append(h.reshape(-1, 3))
    if not tris:
        return np.zeros((0, 3, 2), np.int64), np.zeros((0, 3))
    return np.concatenate(tris).astype(np.int64), np.concatenate(hs)


def _reg(full, r0, c0, s, u, v, n, strips=None):
    """Regular surface for a stack of patches (origins ``r0, c0`` broadcast over the grid;
    ``strips``: their snapped edges, see :func:`_tri_heights`)."""
    r0 = r0[:, None, None]
    c0 = c0[:, None, None]
    return _tri_heights(full, r0, c0, s, u, v, n, strips)


def screen_errors(
    patches: Patches,
    grid: BlockGrid,
    camera: Camera,
    heights: Callable[[int], np.ndarray],
) -> np.ndarray:
    """Pixel distances between true and LOD projections of every full-res sample in view,
    each sample once (:func:`sample_errors`; patch and block borders are drawn twice)."""
    k = grid.k
    rs, cs, ht, hl = [], [], [], []
    for b, rows, cols, hlod in lod_surface(patches, k, heights):
        full = heights(b)
        htrue = full[rows, cols]
        ok = np.isfinite(hlod) & np.isfinite(htrue)
        if not ok.any():
            continue
        br, bc = (int(v) for v in patches.blocks[b])
        rs.append(br * grid.step + rows[ok])
        cs.append(bc * grid.step + cols[ok])
        ht.append(htrue[ok])
        hl.append(hlod[ok])
    if not rs:
        return np.zeros(0)
    cat = np.concatenate
    return sample_errors(grid, camera, cat(rs), cat(cs), cat(ht), cat(hl))


def sample_errors(
    grid: BlockGrid,
    camera: Camera,
    rows: np.ndarray,
    cols: np.ndarray,
    htrue: np.ndarray,
    hlod: np.ndarray,
) -> np.ndarray:
    """One error per distinct global sample ``(rows, cols)`` in view: the largest pixel
    distance of its drawn heights ``hlod`` from its true projection (a sample on a shared edge
    is drawn by several triangles; counting it once per triangle skews p99 and mean)."""
    x, y = grid.sample_xy(rows, cols)
    err, keep = pixel_errors(camera, x, y, htrue, hlod, with_index=True)
    if not err.size:
        return err
    key = (
        np.asarray(rows, np.int64)[keep] * (grid.cols * grid.step + 1)
        + np.asarray(cols, np.int64)[keep]
    )
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    return np.maximum.reduceat(err[order], starts)


def pixel_errors(
    camera: Camera,
    x: np.ndarray,
    y: np.ndarray,
    htrue: np.ndarray,
    hlod: np.ndarray,
    with_index: bool = False,
) -> Any:
    """Pixel distance between the projections of ``(x, y, htrue)`` and ``(x, y, hlod)``, for
    the points whose true projection is in the viewport and the depth range (``with_index``:
    also the indices of those points). A drawn point ``(x, y, hlod)`` outside the depth range
    (nearer than the near plane, behind the eye, beyond the far plane) is clipped, drawn nowhere
    on screen: it counts as :func:`clipped_px`, not as its projection through the eye (tens of
    thousands of px) nor, behind the eye, as nothing."""
    px0, py0, d0, keep = project_in_view(camera, x, y, htrue)
    px1, py1, d1 = camera.project(
        np.stack([np.asarray(x)[keep], np.asarray(y)[keep], np.asarray(hlod)[keep]], -1)
    )
    with np.errstate(invalid="ignore"):
        drawn = (d1 >= camera.near) & (d1 <= camera.far)
        err = np.where(drawn, np.hypot(px1 - px0, py1 - py0), clipped_px(camera))
    return (err, keep) if with_index else err


def clipped_px(camera: Camera) -> float:
    """The error a sample counts whose drawn point the depth range clips: the viewport's
    diagonal, which no displacement between two points on screen exceeds."""
    w, h = camera.viewport
    return float(np.hypot(w, h))


def project_in_view(
    camera: Camera, x: np.ndarray, y: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(px, py, depth)`` of the points ``(x, y, z)`` that lie in the viewport and depth range,
    and the indices of those points (one projection, ``Camera.project``'s arithmetic)."""
    w, h = camera.viewport
    px, py, d = camera.project(np.stack([x, y, z], -1))
    with np.errstate(invalid="ignore"):
        view = (d >= camera.near) & (d <= camera.far) & (px >= 0) & (px <= w)
        view &= (py >= 0) & (py <= h)
    keep = np.flatnonzero(view)
    return px[keep], py[keep], d[keep], keep


def error_stats(err: np.ndarray) -> ErrorStats:
    """Max, 99th percentile and mean of measured errors; NaN for each when no sample was
    measured (the drawn surface covers no in-view sample: nothing was measured, which is not an
    error of 0 px; JSON ``null``, ``nan`` in the tables)."""
    if err.size == 0:
        return ErrorStats(math.nan, math.nan, math.nan, 0)
    return ErrorStats(
        float(err.max()), float(np.percentile(err, 99)), float(err.mean()), int(err.size)
    )


def psnr(a: np.ndarray, b: np.ndarray, cap_db: float = 100.0) -> float:
    """PSNR in dB of two uint8 images (``cap_db`` when identical)."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    if mse == 0.0:
        return cap_db
    return min(cap_db, 10.0 * np.log10(255.0**2 / mse))


def changed_share(a: np.ndarray, b: np.ndarray, threshold: int = 2) -> float:
    """Share of pixels whose largest channel difference exceeds ``threshold`` levels."""
    d = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=-1)
    return float((d > threshold).mean())


def is_clear(img: np.ndarray, clear_rgb: tuple[int, int, int]) -> np.ndarray:
    """Boolean image: the pixel has exactly the clear colour."""
    return (img[..., :3] == np.asarray(clear_rgb, dtype=img.dtype)).all(axis=-1)


def crack_pixels(
    img: np.ndarray,
    footprint: np.ndarray,
    clear_rgb: tuple[int, int, int],
    max_iter: int = 4096,
    holes: np.ndarray | None = None,
) -> int:
    """Clear-colour pixels of ``img`` inside ``footprint`` that the outside cannot reach.

    Pixels joined to the background (outside ``footprint`` or the image border) through clear
    pixels are outline differences of a coarser silhouette, not holes, and are not counted.
    Nor are pixels ``holes`` marks: those the same selection covers when its nodata holes are
    drawn, where the view sees through a hole in the data (one the reference hid behind terrain
    that a coarser silhouette in front of it reveals), not through a crack.
    """
    return int(crack_mask(img, footprint, clear_rgb, max_iter, holes).sum())


def crack_mask(
    img: np.ndarray,
    footprint: np.ndarray,
    clear_rgb: tuple[int, int, int],
    max_iter: int = 4096,
    holes: np.ndarray | None = None,
    border: bool = True,
) -> np.ndarray:
    """The pixels :func:`crack_pixels` counts, as a boolean image. ``border=False``: the image
    border does not reach in (only the outside of ``footprint`` does), so the clear pixels that
    only the border reaches are kept too: a crack running off the image's edge, or an outline
    difference there, which :func:`render.cracks.rays_below` tells apart."""
    clear = is_clear(img, clear_rgb)
    reach = clear & ~footprint
    if border:
        reach[0] |= clear[0]
        reach[-1] |= clear[-1]
        reach[:, 0] |= clear[:, 0]
        reach[:, -1] |= clear[:, -1]
    for _ in range(max_iter):
        grow = reach.copy()
        grow[1:] |= reach[:-1]
        grow[:-1] |= reach[1:]
        grow[:, 1:] |= reach[:, :-1]
        grow[:, :-1] |= reach[:, 1:]
        grow &= clear
        if (grow == reach).all():
            break
        reach = grow
    counted = clear & footprint & ~reach
    if holes is not None:
        counted &= ~holes
    return counted


def heights_fn(store: TerrainStore, patches: Patches) -> Callable[[int], np.ndarray]:
    """Full-resolution float64 grids (NaN where masked) of ``patches.blocks[i]``, cached."""
    cache: dict[int, np.ndarray] = {}

    def get(i: int) -> np.ndarray:
        if i not in cache:
            b = tuple(int(v) for v in patches.blocks[i])
            g = store.read_block(b).astype(np.float64)
            if store.index.has_nodata[b]:
                g[~store.read_mask(b)] = np.nan
            cache[i] = g
        return cache[i]

    return get
