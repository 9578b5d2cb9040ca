"""What share of the terrain in view the drawn surface covers (pure numpy, no GL).

The *in-view samples* of a camera are the full-resolution samples of every node the reference
selection (every visible node at full resolution) holds whose position projects into the
viewport and depth range: terrain samples at their true height, nodata samples (the DEM's own
masked samples; the store's padding beyond the DEM's last row and column is not nodata) at the
middle of the terrain's height range. :func:`coverage` gives the share of in-view terrain samples
the drawn triangles cover, the share of in-view nodata samples they cover (a hole drawn over), and
the terrain samples that lie in the lateral view in front of the camera but nearer than its near
plane (clipped by it, so not measured as error). A view with no terrain sample in it is an error
(:class:`render.errors.EmptyViewError`), not a perfect row.

The screen error counts drawn samples only, so a rule that drops terrain could look perfect;
:func:`uncovered_px` measures how far the dropped terrain lies from the drawn terrain on screen
(the nodata rule ``"gap"`` claims at most ``min(τ, 1)`` px, :mod:`streamer.nodata`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from render import cracks, measure
from render.errors import EmptyViewError
from render.select import Patches

__all__ = [
    "Coverage",
    "EmptyViewError",
    "coverage",
    "in_view_samples",
    "near_clipped_samples",
    "percent",
    "reference_cover",
    "uncovered_px",
]
from streamer.camera import Camera
from tiler.grid import BlockGrid
from tiler.store import TerrainStore


@dataclass(frozen=True)
class Coverage:
    """Coverage figures of one drawn view (see the module doc)."""

    terrain_in_view: int
    nodata_in_view: int
    terrain_covered: float  # share of in-view terrain samples under the drawn surface
    nodata_covered: float  # share of in-view nodata samples under it (0 when none in view)
    near_clipped: int  # terrain samples in the lateral view nearer than the near plane
    uncovered_px: float = 0.0  # undrawn terrain's screen distance to drawn terrain (px)
    #: in-view terrain samples neither the drawn triangles nor the reference's full-resolution
    #: ones cover (each triangle holding them has a nodata corner): left out of
    #: ``terrain_in_view``, the shares and ``uncovered_px``
    undrawable: int = 0


def in_view_samples(
    ref: Patches, grid: BlockGrid, camera: Camera, heights: Callable[[int], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, int]:
    """Global keys (``row * (cols * step + 1) + col``) of the in-view terrain samples and
    in-view nodata samples of the reference selection ``ref``, and the near-clipped count."""
    terrain, _, nodata, clipped = _in_view(ref, grid, camera, heights)
    return terrain, nodata, clipped


def _in_view(
    ref: Patches, grid: BlockGrid, camera: Camera, heights: Callable[[int], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """:func:`in_view_samples` with the terrain samples' heights (second, same order)."""
    wg = grid.cols * grid.step + 1
    terrain, nodata, clipped, th = [], [], [], []
    zs = []
    for b, rows, cols, _ in measure.lod_surface(ref, grid.k, heights):
        h = heights(b)[rows, cols]
        br, bc = (int(v) for v in ref.blocks[b])
        gr, gc = br * grid.step + rows, bc * grid.step + cols
        ok = np.isfinite(h)
        x, y = grid.sample_xy(gr, gc)
        _, _, _, keep = measure.project_in_view(camera, x[ok], y[ok], h[ok])
        terrain.append((gr[ok] * wg + gc[ok])[keep])
        th.append(h[ok][keep])
        if ok.any():
            zs.append((float(h[ok].min()), float(h[ok].max())))
        clipped.append((gr[ok] * wg + gc[ok])[_near_clipped(camera, x[ok], y[ok], h[ok])])
        # masked samples inside the DEM's extent are nodata; those beyond it are the store's
        # padding of its last block row and column, not part of the DEM
        nd = ~ok & (gr < grid.height) & (gc < grid.width)
        if nd.any():
            nodata.append((gr[nd], gc[nd], x[nd], y[nd]))
    zmid = 0.5 * (min(z[0] for z in zs) + max(z[1] for z in zs)) if zs else 0.0
    nd = []
    for gr, gc, x, y in nodata:
        _, _, _, keep = measure.project_in_view(camera, x, y, np.full(x.shape, zmid))
        nd.append((gr * wg + gc)[keep])
    cat = lambda parts: np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)  # noqa: E731
    keys, first = (
        np.unique(np.concatenate(terrain), return_index=True)
        if terrain
        else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    )
    zs_t = np.concatenate(th)[first] if th else np.zeros(0)
    return keys, zs_t, cat(nd), len(cat(clipped))


def percent(share: float) -> str:
    """``share`` (0..1) as a percentage with one decimal for the tables, never rounded to a
    reading it is not: a share above 0 but below 0.05 % is ``<0.1%`` (a few nodata samples drawn
    over, not none), one below 1 but above 99.95 % is ``>99.9%`` (not all the terrain drawn)."""
    text = f"{100 * share:.1f}%"
    if text == "0.0%" and share > 0.0:
        return "<0.1%"
    if text == "100.0%" and share < 1.0:
        return ">99.9%"
    return text


def _cut(shift: int, n: int) -> slice:
    """The part of an axis of length ``n`` that a shift by ``shift`` lands on."""
    return slice(max(0, shift), n - max(0, -shift))


def uncovered_px(
    grid: BlockGrid,
    camera: Camera,
    terrain: np.ndarray,
    heights: np.ndarray,
    covered: np.ndarray,
    radius: int = 256,
) -> float:
    """Largest screen distance (px) from an uncovered in-view terrain sample to a covered
    in-view terrain sample near it on the sample lattice (both at their heights; found by
    Euclidean-min propagation over 8 neighbours, at most ``radius`` rounds); 0 when every one
    is covered, ``inf`` when one is left without a covered sample. ``terrain``: sorted global
    keys, ``heights`` theirs, ``covered``: their covered mask. The sample found need not be the
    nearest on screen, so the figure is at least the distance to the nearest drawn sample."""
    if covered.all() or not len(terrain):
        return 0.0
    if not covered.any():
        return float("inf")
    wg = grid.cols * grid.step + 1
    rows, cols = terrain // wg, terrain % wg
    r0, c0 = int(rows.min()), int(cols.min())
    shape = (int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1)
    rr, cc = rows - r0, cols - c0
    # nearest covered sample per lattice point by Euclidean-min propagation over 8 neighbours
    big = np.iinfo(np.int64).max // 4
    near_r = np.full(shape, -1, np.int64)
    near_c = np.full(shape, -1, np.int64)
    near_r[rr[covered], cc[covered]] = rr[covered]
    near_c[rr[covered], cc[covered]] = cc[covered]
    gr, gc = np.mgrid[0 : shape[0], 0 : shape[1]]
    dist = np.where(near_r >= 0, 0, big)
    todo_r, todo_c = rr[~covered], cc[~covered]
    stop = radius  # once all are reached at step i, a Euclidean-nearer one is within 1.5 i
    for i in range(1, radius + 1):
        if i > stop:
            break
        changed = False
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
            src = (_cut(-dr, shape[0]), _cut(-dc, shape[1]))
            dst = (_cut(dr, shape[0]), _cut(dc, shape[1]))
            cr, ccol = near_r[src], near_c[src]
            d = np.where(cr >= 0, (gr[dst] - cr) ** 2 + (gc[dst] - ccol) ** 2, big)
            better = d < dist[dst]
            if better.any():
                changed = True
                dist[dst] = np.where(better, d, dist[dst])
                near_r[dst] = np.where(better, cr, near_r[dst])
                near_c[dst] = np.where(better, ccol, near_c[dst])
        if not changed:
            break
        if stop == radius and (near_r[todo_r, todo_c] >= 0).all():
            stop = min(radius, int(np.ceil(1.5 * i)) + 1)
    nr, nc = near_r[todo_r, todo_c], near_c[todo_r, todo_c]
    if (nr < 0).any():
        return float("inf")
    lookup = np.searchsorted(terrain, (nr + r0) * wg + (nc + c0))
    pts = []
    for r_, c_, z_ in (
        (todo_r + r0, todo_c + c0, heights[~covered]),
        (nr + r0, nc + c0, heights[lookup]),
    ):
        x, y = grid.sample_xy(r_, c_)
        pts.append(np.stack(camera.project(np.stack([x, y, z_], -1))[:2], -1))
    return float(np.hypot(*(pts[0] - pts[1]).T).max())


def _near_clipped(camera: Camera, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Mask of the points in the lateral view (inside the viewport's sides) in front of the
    camera but nearer than its near plane."""
    if not len(x):
        return np.zeros(0, bool)
    w, h = camera.viewport
    px, py, d = camera.project(np.stack([x, y, z], -1))
    with np.errstate(invalid="ignore"):
        lat = (px >= 0) & (px <= w) & (py >= 0) & (py <= h)
        return lat & (d > 0) & (d < camera.near)


def near_clipped_samples(store: TerrainStore, camera: Camera) -> int:
    """Terrain samples of ``store`` in the lateral view in front of ``camera`` but nearer than
    its near plane: every one, not only those of the nodes a selection kept (a selection culls
    the nodes wholly nearer than the near plane, so their samples went uncounted: 278 of 1,327
    with a 1,400 m near plane on a 65² DEM). A block none of whose samples can lie within the
    near rectangle's reach of the eye (its box, heights included, farther) is not read."""
    g = store.grid
    w, h = camera.viewport
    tx, ty = 0.5 * w / camera.focal_px, 0.5 * h / camera.focal_px
    reach = camera.near * float(np.sqrt(1.0 + tx * tx + ty * ty))  # the near corners' distance
    ex, ey, ez = (float(v) for v in camera.eye)
    wg = g.cols * g.step + 1
    blk = np.asarray(store.blocks(), dtype=np.int64).reshape(-1, 2)
    xa, ya = g.sample_xy(blk[:, 0] * g.step, blk[:, 1] * g.step)
    xb, yb = g.sample_xy((blk[:, 0] + 1) * g.step, (blk[:, 1] + 1) * g.step)
    zlo, zhi = (np.asarray(z, np.float64)[blk[:, 0], blk[:, 1]] for z in
                (store.index.zmin, store.index.zmax))  # fmt: skip
    gap = np.zeros(len(blk))
    for lo, hi, e in ((np.minimum(xa, xb), np.maximum(xa, xb), ex),
                      (np.minimum(ya, yb), np.maximum(ya, yb), ey), (zlo, zhi, ez)):  # fmt: skip
        gap += np.maximum(np.maximum(lo - e, e - hi), 0.0) ** 2
    with np.errstate(invalid="ignore"):
        near = ~(np.sqrt(gap) >= reach)  # (a block without a height range is read)
    keys = []
    for b in map(tuple, blk[near].tolist()):
        r0, c0 = b[0] * g.step, b[1] * g.step
        z = store.read_block(b).astype(np.float64)
        valid = store.read_mask(b) if store.index.has_nodata[b] else np.ones(z.shape, bool)
        rr, cc = np.nonzero(valid & np.isfinite(z))
        gr, gc = r0 + rr, c0 + cc
        inside = (gr < g.height) & (gc < g.width)  # (not the store's padding)
        gr, gc, zz = gr[inside], gc[inside], z[rr[inside], cc[inside]]
        x, y = g.sample_xy(gr, gc)
        keys.append((gr * wg + gc)[_near_clipped(camera, x, y, zz)])
    return len(np.unique(np.concatenate(keys))) if keys else 0


def reference_cover(
    grid: BlockGrid,
    ref: Patches,
    heights: Callable[[int], np.ndarray],
    keys: np.ndarray | None = None,
) -> np.ndarray:
    """Sorted global keys of the samples the reference selection's own triangles cover: a
    terrain sample outside them (every triangle holding it has a nodata corner) cannot be
    drawn at full resolution. With ``keys`` (sorted), only those of ``keys``, from the
    reference patches that hold one of them."""
    if keys is not None:
        ref = ref.subset(_patches_holding(ref, grid, keys))
    tri, h = cracks.drawn(*measure.patch_triangles(ref, grid, heights))
    if not len(tri):
        return np.zeros(0, np.int64)
    rows, cols, _ = measure.rasterise(tri, h)
    wg = grid.cols * grid.step + 1
    out = np.unique(np.asarray(rows, np.int64) * wg + np.asarray(cols, np.int64))
    return out if keys is None else out[np.isin(out, keys, assume_unique=True)]


def _patches_holding(ref: Patches, grid: BlockGrid, keys: np.ndarray) -> np.ndarray:
    """Per patch of ``ref``: its closed footprint holds one of the samples ``keys`` (a summed
    table of the samples per block, so the test is O(1) per patch)."""
    keep = np.zeros(len(ref), bool)
    if not len(ref) or not len(keys):
        return keep
    wg = grid.cols * grid.step + 1
    step, side = grid.step, grid.step + 1
    rows, cols = keys // wg, keys % wg
    e = np.left_shift(np.left_shift(1, ref.cells_log2), grid.k - ref.level)
    r0, c0 = ref.row * e, ref.col * e  # in-block sample origin of each patch
    pb = ref.blocks[ref.block]
    for br, bc in ref.blocks.tolist():
        lr, lc = rows - br * step, cols - bc * step  # (a border sample is in two blocks)
        inside = (lr >= 0) & (lr <= step) & (lc >= 0) & (lc <= step)
        mine = (pb[:, 0] == br) & (pb[:, 1] == bc)
        if not inside.any() or not mine.any():
            continue
        sat = np.zeros((side + 1, side + 1), np.int64)
        np.add.at(sat, (lr[inside] + 1, lc[inside] + 1), 1)
        sat = sat.cumsum(0).cumsum(1)
        a, b = r0[mine], c0[mine]
        a1, b1 = np.minimum(a + e[mine], step) + 1, np.minimum(b + e[mine], step) + 1
        keep[mine] = (sat[a1, b1] - sat[a, b1] - sat[a1, b] + sat[a, b]) > 0
    return keep


def coverage(
    grid: BlockGrid,
    camera: Camera,
    ref: Patches,
    heights: Callable[[int], np.ndarray],
    tri_cr: np.ndarray,
    tri_h: np.ndarray,
    store: TerrainStore | None = None,
    near_clipped: int | None = None,
) -> Coverage:
    """Coverage of the drawn triangles (global ``(col, row)`` corners, drawn heights) over
    the in-view samples of the reference selection ``ref`` that a triangle can draw: those the
    drawn triangles or the reference's own full-resolution ones cover (:func:`reference_cover`,
    read for the missed samples only); :class:`EmptyViewError` when the view holds no terrain
    sample. With ``store``, the near-clipped count is every such sample of the store
    (:func:`near_clipped_samples`; ``near_clipped``: that count, computed once for a camera
    drawn at several τ), else those of ``ref``'s nodes."""
    terrain, terrain_h, nodata, clipped = _in_view(ref, grid, camera, heights)
    if near_clipped is not None:
        clipped = near_clipped
    elif store is not None:
        clipped = near_clipped_samples(store, camera)
    if not len(terrain):
        raise EmptyViewError(
            f"the view from {tuple(round(v, 1) for v in camera.position)} (yaw {camera.yaw:g}, "
            f"pitch {camera.pitch:g}) holds no terrain sample ({len(nodata)} nodata samples, "
            f"{clipped} terrain samples nearer than the near plane {camera.near:g}): "
            "its error, crack and coverage figures would be vacuous; aim the camera at the "
            "terrain"
        )
    tri, h = cracks.drawn(tri_cr, tri_h)
    rows, cols, _ = measure.rasterise(tri, h) if len(tri) else (np.zeros(0, np.int64),) * 3
    wg = grid.cols * grid.step + 1
    covered = np.unique(np.asarray(rows, np.int64) * wg + np.asarray(cols, np.int64))
    hit = np.isin(terrain, covered, assume_unique=True)
    undrawable = 0
    if not hit.all():  # is it terrain that no triangle can draw (isolated beside nodata)?
        missed = terrain[~hit]
        drawable = hit | np.isin(terrain, reference_cover(grid, ref, heights, missed))
        undrawable = int((~drawable).sum())
        if drawable.any():
            terrain, terrain_h, hit = terrain[drawable], terrain_h[drawable], hit[drawable]
    t = float(hit.mean())
    n = float(np.isin(nodata, covered, assume_unique=True).mean()) if len(nodata) else 0.0
    gap = uncovered_px(grid, camera, terrain, terrain_h, hit)
    return Coverage(len(terrain), len(nodata), t, n, clipped, gap, undrawable)
