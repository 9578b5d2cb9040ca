"""Cracks measured on what is drawn (pure numpy, no GL).

Two kinds of figures (docs/RENDER.md, "Measurements"):

* **Watertightness** (:func:`watertight`), exact and camera-independent, from the drawn
  triangles read back as global sample-lattice ``(col, row)`` corners and drawn heights: an
  edge used by one triangle only is *open*; it is on the drawn region's outer boundary unless
  another open edge covers the same lattice segment from the other side (a T-junction, or a
  gap between two pieces that do not share vertices). ``open_edges`` counts the open edges that
  are not on the outer boundary; ``gap_edges`` those of them whose two sides do not meet in 3-D
  (height mismatch above a float32 tolerance: a height-adjusted T-junction is open but not a
  gap); ``max_gap_m`` is the largest vertical opening (metres) over those segments and over
  lattice points drawn with different heights by different triangles; ``longest_gap_m`` the
  longest gap edge (metres in x/y).
* **Crack pixels** of a drawn image (:func:`render.measure.crack_pixels`) seen from the
  measured camera and from above (:func:`above_camera`: a nadir camera framing the drawn
  triangles), counted in :func:`render.pipeline.tradeoff`. From above, a clear pixel counts
  only when its ray goes below the drawn surface (:func:`rays_below`): through a gap in it.
  A ray that stays above the surface wherever it passes over it and leaves past its edge sees
  the background past a ridge (steep relief folds over itself in a wide-angle picture), which
  is no crack.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from render import measure
from render.gpu import MASKED_BELOW
from streamer.camera import Camera
from tiler.grid import BlockGrid

#: heights closer than this (metres, plus ``REL_TOL`` × |height|) meet (float32 read-back)
ABS_TOL = 1e-3
REL_TOL = 1e-6


@dataclass(frozen=True)
class Watertight:
    """Exact watertightness of a drawn triangle mesh (see the module doc)."""

    triangles: int  # drawn (non-hidden, non-degenerate) triangles examined
    boundary_edges: int  # open edges on the drawn region's outer boundary
    open_edges: int  # open edges not on the outer boundary (T-junctions and gaps)
    gap_edges: int  # of those, the ones whose two sides do not meet in 3-D
    max_gap_m: float  # largest vertical opening, metres
    longest_gap_m: float  # longest gap edge, metres in x/y


def drawn(tri_cr: np.ndarray, tri_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The drawn triangles of a read-back: hidden (NaN or masked corner) and zero-area ones
    removed; ``(m, 3, 2)`` int64 and ``(m, 3)`` float64."""
    tri = np.asarray(tri_cr, dtype=np.int64).reshape(-1, 3, 2)
    h = np.asarray(tri_h, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(h).all(axis=1) & (h > MASKED_BELOW).all(axis=1)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    ok &= e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] != 0
    return tri[ok], h[ok]


def _tol(h: np.ndarray) -> np.ndarray:
    return ABS_TOL + REL_TOL * np.abs(h)


def _spread(keys: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per distinct key (sorted): ``(keys, max - min of vals, index of each input's group)``."""
    order = np.lexsort(keys.T[::-1])
    ks, vs = keys[order], vals[order]
    new = np.ones(len(ks), dtype=bool)
    new[1:] = (ks[1:] != ks[:-1]).any(axis=1)
    starts = np.flatnonzero(new)
    spread = np.maximum.reduceat(vs, starts) - np.minimum.reduceat(vs, starts)
    group = np.empty(len(ks), np.int64)
    group[order] = np.cumsum(new) - 1
    return ks[starts], spread, group


def watertight(grid: BlockGrid, tri_cr: np.ndarray, tri_h: np.ndarray) -> Watertight:
    """Open, gap and boundary edges and the largest gap of a drawn mesh (global ``(col,
    row)`` corners ``(m, 3, 2)``, drawn heights ``(m, 3)``; hidden triangles are left out)."""
    tri, h = drawn(tri_cr, tri_h)
    if not len(tri):
        return Watertight(0, 0, 0, 0, 0.0, 0.0)
    # lattice points drawn with different heights by different triangles
    pts = tri.reshape(-1, 2)
    _, spread, _ = _spread(pts, h.ravel())
    vmax = float(spread.max())
    vtol = float(_tol(np.array([np.abs(h).max()]))[0])
    vertex_gap = vmax if vmax > vtol else 0.0
    # edges: canonical (lower end first), counted
    a = np.concatenate([tri[:, j] for j in range(3)])
    b = np.concatenate([tri[:, (j + 1) % 3] for j in range(3)])
    ha = np.concatenate([h[:, j] for j in range(3)])
    hb = np.concatenate([h[:, (j + 1) % 3] for j in range(3)])
    swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
    a, b = np.where(swap[:, None], b, a), np.where(swap[:, None], a, b)
    ha, hb = np.where(swap, hb, ha), np.where(swap, ha, hb)
    key = np.concatenate([a, b], 1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    open_ = counts[inv.ravel()] == 1
    a, b, ha, hb = a[open_], b[open_], ha[open_], hb[open_]
    if not len(a):
        return Watertight(len(tri), 0, 0, 0, vertex_gap, 0.0)
    # open edges cut into primitive lattice segments; a segment covered twice is interior
    d = b - a
    g = np.gcd(np.abs(d[:, 0]), np.abs(d[:, 1]))
    unit = d // g[:, None]
    edge = np.repeat(np.arange(len(a)), g)
    first = np.repeat(np.cumsum(g) - g, g)
    t = np.arange(len(edge)) - first
    gg = g[edge].astype(np.float64)
    p0 = a[edge] + t[:, None] * unit[edge]
    h0 = ha[edge] + (hb[edge] - ha[edge]) * (t / gg)
    h1 = ha[edge] + (hb[edge] - ha[edge]) * ((t + 1) / gg)
    seg = np.concatenate([p0, unit[edge]], 1)  # a's end is the lower one: unit is canonical
    _, s0, grp = _spread(seg, h0)
    _, s1, _ = _spread(seg, h1)
    gcount = np.bincount(grp)
    interior = gcount[grp] >= 2
    gap = np.maximum(s0, s1)[grp]
    gap_seg = interior & (gap > _tol(np.maximum(np.abs(h0), np.abs(h1))))
    inner_edge = np.zeros(len(a), bool)
    inner_edge[edge[interior]] = True
    gap_edge = np.zeros(len(a), bool)
    gap_edge[edge[gap_seg]] = True
    max_gap = max(vertex_gap, float(gap[gap_seg].max()) if gap_seg.any() else 0.0)
    longest = 0.0
    if gap_edge.any():
        xa, ya = grid.sample_xy(a[gap_edge, 1], a[gap_edge, 0])
        xb, yb = grid.sample_xy(b[gap_edge, 1], b[gap_edge, 0])
        longest = float(np.hypot(xb - xa, yb - ya).max())
    return Watertight(
        triangles=len(tri),
        boundary_edges=int((~inner_edge).sum()),
        open_edges=int(inner_edge.sum()),
        gap_edges=int(gap_edge.sum()),
        max_gap_m=max_gap,
        longest_gap_m=longest,
    )


def above_camera(grid: BlockGrid, camera: Camera, tri_cr: np.ndarray, tri_h: np.ndarray) -> Camera:
    """A straight-down camera framing the drawn triangles (the measured view's selection seen
    from above), with the measured camera's viewport and field of view."""
    tri, h = drawn(tri_cr, tri_h)
    if not len(tri):
        x, y = grid.sample_xy(np.array([0, grid.height - 1]), np.array([0, grid.width - 1]))
        zlo = zhi = 0.0
    else:
        x, y = grid.sample_xy(tri[..., 1].ravel(), tri[..., 0].ravel())
        zlo, zhi = float(h.min()), float(h.max())
    cx, cy = 0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max())
    diag = max(math.hypot(x.max() - x.min(), y.max() - y.min()), 1.0)
    w, hh = camera.viewport
    aspect = min(1.0, w / hh)
    dist = 0.5 * diag / math.tan(math.radians(camera.fov_y) / 2) / aspect
    top = zhi + dist
    return Camera(
        (float(cx), float(cy), top),
        pitch=-90.0,
        fov_y=camera.fov_y,
        viewport=camera.viewport,
        near=max(0.1, 0.5 * dist),
        far=top - zlo + 0.5 * dist + 1.0,
    )


def rays_below(
    grid: BlockGrid,
    camera: Camera,
    tri_cr: np.ndarray,
    tri_h: np.ndarray,
    pixels: np.ndarray,
    chunk: int = 1 << 19,
) -> np.ndarray:
    """Per pixel ``(row, col)`` of ``camera``'s image (rows of ``pixels``): does the ray
    through its centre pass below the drawn surface (the triangles ``tri_cr``/``tri_h``, hidden
    ones left out) somewhere over it, by more than the float32 tolerance? Exact float64
    geometry: the ray's ground track is clipped to each triangle and its height above the
    triangle's plane, linear along the track, is read at the clipped ends (down to the lowest
    drawn height). False for a ray that stays above the surface wherever it passes over it:
    background seen past a ridge (or past the mesh's edge), not through a gap."""
    px = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    out = np.zeros(len(px), dtype=bool)
    tri, h = drawn(tri_cr, tri_h)
    if not len(px) or not len(tri):
        return out
    x, y = grid.sample_xy(tri[..., 1], tri[..., 0])  # (m, 3) each
    e = camera.eye
    x, y = x - e[0], y - e[1]  # eye-relative: UTM metres keep their precision
    z = h - e[2]
    ax, ay, az = x[:, 0], y[:, 0], z[:, 0]
    ux, uy, uz = x[:, 1] - ax, y[:, 1] - ay, z[:, 1] - az
    vx, vy, vz = x[:, 2] - ax, y[:, 2] - ay, z[:, 2] - az
    den = ux * vy - vx * uy  # non-zero: drawn() dropped zero-area triangles
    gx, gy = (uz * vy - vz * uy) / den, (ux * vz - vx * uz) / den  # the plane's slope
    sgn = np.sign(den)
    # edges i -> i+1 with inward normals (counter-clockwise after the orientation sign)
    ex = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 1], x[:, 0] - x[:, 2]], 1)
    ey = np.stack([y[:, 1] - y[:, 0], y[:, 2] - y[:, 1], y[:, 0] - y[:, 2]], 1)
    nx, ny = -ey * sgn[:, None], ex * sgn[:, None]
    tol = _tol(np.abs(h).max(axis=1))
    w, hh = camera.viewport
    f = camera.focal_px
    sx = (px[:, 1] + 0.5 - w / 2.0) / f
    sy = (hh / 2.0 - (px[:, 0] + 0.5)) / f
    d = camera.forward[None, :] + sx[:, None] * camera.right + sy[:, None] * camera.up
    zlo = float(h.min()) - e[2]
    step = max(1, chunk // len(tri))
    for s0 in range(0, len(px), step):
        dd = d[s0 : s0 + step]
        dx, dy, dz = dd[:, 0:1], dd[:, 1:2], dd[:, 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_end = np.where(dz < 0.0, (zlo - 1.0) / dz, np.inf)  # down past the lowest point
        lo = np.zeros((len(dd), len(tri)))
        hi = np.broadcast_to(t_end, lo.shape).copy()
        for i in range(3):  # inside edge i: n . (p(t) - v_i) >= 0, linear in t
            a = nx[:, i] * (0.0 - x[:, i]) + ny[:, i] * (0.0 - y[:, i])
            b = nx[:, i] * dx + ny[:, i] * dy
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -a / b
            lo = np.where(b > 0.0, np.maximum(lo, t), lo)
            hi = np.where(b < 0.0, np.minimum(hi, t), hi)
            lo = np.where((b == 0.0) & (a < 0.0), np.inf, lo)  # parallel, outside
        meet = lo <= hi
        with np.errstate(invalid="ignore"):
            # height of the ray above the plane at t: (dz - g.d_xy) t - (az - g.a_xy)
            rate = dz - gx * dx - gy * dy
            off = az - gx * ax - gy * ay
            c_lo = rate * lo - off
            c_hi = np.where(np.isfinite(hi), rate * hi - off, np.where(rate < 0, -np.inf, np.inf))
            below = meet & (np.minimum(c_lo, c_hi) < -tol)
        out[s0 : s0 + step] = below.any(axis=1)
    return out


def border_only(
    img: np.ndarray, footprint: np.ndarray, clear_rgb: tuple[int, int, int]
) -> np.ndarray:
    """Clear pixels of ``img`` inside ``footprint`` that only the image border reaches through
    clear pixels (not the outside of ``footprint``): the ones
    :func:`render.measure.crack_pixels` leaves out for touching the border, where a crack
    running off the image's edge is as likely as an outline difference."""
    wide = measure.crack_mask(img, footprint, clear_rgb, border=False)
    return wide & ~measure.crack_mask(img, footprint, clear_rgb)


def gaps_through(
    grid: BlockGrid,
    camera: Camera,
    mesh: tuple[np.ndarray, np.ndarray],
    pixels: np.ndarray,
    holes: np.ndarray | None = None,
) -> int:
    """How many of the ``pixels`` (a boolean image; ``holes``, when given, left out) look
    through a gap in the drawn ``mesh`` (:func:`rays_below`): the crack pixels among
    :func:`border_only`'s."""
    mask = pixels if holes is None else pixels & ~holes
    rows, cols = np.nonzero(mask)
    if not len(rows):
        return 0
    return int(rays_below(grid, camera, *mesh, np.c_[rows, cols]).sum())
