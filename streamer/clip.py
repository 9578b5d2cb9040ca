"""Clipping planes for a camera over a store (pure): a near plane that follows the camera's
clearance above the terrain and a far plane beyond the whole DEM.

The renderer writes a logarithmic depth (docs/RENDER.md, "Precision and extremes"), so a near
plane of a few centimetres and a far plane of 1,000 km coexist: the near plane is chosen from
the clearance (:func:`near_plane`), the far plane from the scene's size (:func:`reach`)."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np

from streamer.camera import Camera
from tiler.errors import StoreError
from tiler.store import TerrainStore

log = logging.getLogger(__name__)

#: the smallest near plane (m): log depth resolves it together with a far plane of 1e6 km
MIN_NEAR = 0.01


def zrange(store: TerrainStore) -> tuple[float, float]:
    """The lowest block bottom and highest block top of the store (``(0, 0)`` without terrain)."""
    idx = store.index
    with np.errstate(invalid="ignore"):
        lo, hi = float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 0.0
    return lo, hi


def local_top(store: TerrainStore, x: float, y: float, radius: float) -> float:
    """The highest stored block top within ``radius`` (m) of ``(x, y)`` (the global top when
    the store gives no block geometry); ``-inf`` when no block is that near."""
    g, zmax = store.grid, np.asarray(store.index.zmax, dtype=np.float64)
    if not hasattr(g, "block_bounds"):
        return zrange(store)[1]
    br, bc = np.meshgrid(np.arange(zmax.shape[0]), np.arange(zmax.shape[1]), indexing="ij")
    x0, y0, x1, y1 = g.block_bounds(br, bc)
    ddx = np.maximum(np.maximum(x0 - x, x - x1), 0.0)
    ddy = np.maximum(np.maximum(y0 - y, y - y1), 0.0)
    near = (np.hypot(ddx, ddy) <= radius) & np.isfinite(zmax)
    return float(zmax[near].max()) if near.any() else -math.inf


def cell_surface(h: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """Heights at ``(u, v)`` (column and row fractions in ``[0, 1]``) of the cell with corner
    heights ``h`` (``[[NW, NE], [SW, SE]]``, rows growing south) cut along each diagonal: the
    ``NW-SE`` one (``render.mesh``'s ``a-d`` cut: triangles NW-NE-SE and NW-SE-SW) and the
    ``NE-SW`` one."""
    nw, ne, sw, se = float(h[0, 0]), float(h[0, 1]), float(h[1, 0]), float(h[1, 1])
    upper, left = u >= v, u + v <= 1.0  # the triangle of each cut holding (u, v)
    a_d = nw + u * (ne - nw) + v * (se - ne) if upper else nw + v * (sw - nw) + u * (se - sw)
    b_c = (
        nw + u * (ne - nw) + v * (sw - nw)
        if left
        else se + (1 - u) * (sw - se) + (1 - v) * (ne - se)
    )
    return a_d, b_c


def ground_height(
    store: TerrainStore, x: float, y: float, cache: dict | None = None
) -> float | None:
    """The height at ``(x, y)`` of the full-resolution triangulated surface, the lower of the
    cell's two triangulations (:func:`cell_surface`: the renderer's patch meshes cut every cell
    along its ``NW-SE`` diagonal, but ``jung-han`` alternates the diagonal and the tessellator's
    is the implementation's, so the terrain drawn at full resolution there is no lower);
    ``None`` outside the DEM or where a corner of the cell is nodata. Reads one block (kept in
    ``cache``, when given, for the next point)."""
    g = store.grid
    row, col = g.world_to_sample(x, y)
    if not (0.0 <= row <= g.height - 1 and 0.0 <= col <= g.width - 1):
        return None
    r0 = min(int(math.floor(row)), g.height - 2)
    c0 = min(int(math.floor(col)), g.width - 2)
    block = tuple(int(v) for v in g.block_of_sample(r0, c0))
    if not store.index.exists[block]:
        return None
    got = cache.get(block) if cache is not None else None
    if got is None:
        heights = np.asarray(store.read_block(block), dtype=np.float64)
        mask = store.read_mask(block) if store.index.has_nodata[block] else None
        got = (heights, mask)
        if cache is not None:
            cache[block] = got
    heights, mask = got
    r, c = r0 - block[0] * g.step, c0 - block[1] * g.step
    h = heights[r : r + 2, c : c + 2]
    if mask is not None and not mask[r : r + 2, c : c + 2].all():
        return None
    if not np.isfinite(h).all():
        return None
    u = min(max(float(col) - c0, 0.0), 1.0)
    v = min(max(float(row) - r0, 0.0), 1.0)
    return min(cell_surface(h, u, v))


def ground_clearance(store: TerrainStore, eyes: np.ndarray, within: float = 0.0) -> np.ndarray:
    """Per eye ``(x, y, z)`` (rows of ``eyes``): its height above the terrain under it
    (:func:`ground_height`; negative below it). ``inf`` for an eye at least ``within`` metres
    above its block's highest point (nothing read: it is at least that high), NaN where the
    terrain under it is unknown (off the DEM, nodata, a block that cannot be read). Each block
    is read once."""
    eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(eyes), np.nan)
    g, zmax = store.grid, np.asarray(store.index.zmax, dtype=np.float64)
    rows, cols = g.world_to_sample(eyes[:, 0], eyes[:, 1])
    inside = (rows >= 0) & (rows <= g.height - 1) & (cols >= 0) & (cols <= g.width - 1)
    cache: dict = {}
    for i in np.flatnonzero(inside):
        r0 = min(int(math.floor(rows[i])), g.height - 2)
        c0 = min(int(math.floor(cols[i])), g.width - 2)
        br, bc = (int(v) for v in g.block_of_sample(r0, c0))
        if not eyes[i, 2] < zmax[br, bc] + within:  # high above the block's top (or no terrain)
            out[i] = math.inf if math.isfinite(zmax[br, bc]) else math.nan
            continue
        try:
            ground = ground_height(store, eyes[i, 0], eyes[i, 1], cache)
        except (OSError, StoreError):  # a read that fails is the session's to report: unknown
            continue
        if ground is not None:
            out[i] = eyes[i, 2] - ground
    return out


def depth_below_ground(store: TerrainStore, eyes: np.ndarray) -> np.ndarray:
    """Per eye ``(x, y, z)`` (rows of ``eyes``): how far below the terrain under it it is
    (:func:`ground_height`; 0 where it is not, or where that is unknown: a block that cannot be
    read). Only eyes under their block's highest point read a block, each block once."""
    clearance = ground_clearance(store, eyes)
    with np.errstate(invalid="ignore"):
        return np.where(clearance < 0.0, -clearance, 0.0)


def near_reach(camera: Camera) -> float:
    """How far from the eye the near plane reaches (to its corners): ``near * sqrt(1 + T^2)``,
    ``T`` the tangent of the half diagonal FOV. An eye closer than that to the ground has the
    near plane cut the ground in front of it wherever it looks down."""
    return camera.near * math.hypot(1.0, camera.tan_half_diagonal)


def clipped_by_near(clearance: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """Per camera: it is on or above the terrain under it (``clearance`` >= 0, from
    :func:`ground_clearance`) but closer to it than its near plane reaches (:func:`near_reach`):
    the near plane clips the ground it looks at (a blank band, or sky, where terrain is)."""
    c = np.asarray(clearance, dtype=np.float64)
    reach_ = np.array([near_reach(cam) for cam in cameras], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return (c >= 0.0) & (c < reach_)


def warn_path_below_ground(
    store: TerrainStore,
    cameras: Sequence[Camera],
    effect: str,
    logger: logging.Logger | None = None,
) -> np.ndarray:
    """Log a warning (on ``logger``, default this module's) when cameras of a path are below
    the terrain under them, naming how many, the first, how deep, and ``effect`` (what that does
    to the caller's output), and another when cameras are on or just above it, closer than
    their near plane reaches (:func:`clipped_by_near`), naming the first and its clearance;
    each camera's depth below the ground (0: not below, or unknown)."""
    eyes = np.array([c.position for c in cameras], dtype=np.float64).reshape(-1, 3)
    within = max((near_reach(c) for c in cameras), default=0.0)
    clearance = ground_clearance(store, eyes, within)
    with np.errstate(invalid="ignore"):
        depth = np.where(clearance < 0.0, -clearance, 0.0)
    below = np.flatnonzero(depth > 0)
    if len(below):
        (logger or log).warning(
            "%d of the path's %d frames have the camera below the terrain under it (the first: "
            "frame %d, %.1f m below; the deepest %.1f m): %s; raise the path above the ground",
            len(below), len(cameras), below[0], depth[below[0]], depth.max(), effect,
        )  # fmt: skip
    close = np.flatnonzero(clipped_by_near(clearance, cameras)) if len(cameras) else []
    if len(close):
        i = int(close[0])
        (logger or log).warning(
            "%d of the path's %d frames have the camera on or just above the terrain, closer "
            "than its near plane reaches (the first: frame %d, %.3g m above the ground, the "
            "near plane reaching %.3g m): the near plane clips the ground in front of it, so "
            "those frames show sky or nothing where the terrain is; raise the path",
            len(close), len(cameras), i, clearance[i], near_reach(cameras[i]),
        )  # fmt: skip
    return depth


def near_plane(
    store: TerrainStore, eye: tuple[float, float, float], tan_half_diagonal: float, cap: float
) -> float:
    """A near plane (at most ``cap``, at least :data:`MIN_NEAR`) that clips no terrain: half the
    camera's clearance above the highest block top within reach of the near rectangle, divided
    by ``1 + tan_half_diagonal`` (the rectangle's corners reach that far below the eye). An eye
    closer to the ground than :data:`MIN_NEAR` reaches has the ground clipped all the same:
    :func:`clipped_by_near` tells, and ``render.views.warn_below_ground`` warns about it."""
    reach_ = cap * (1.0 + tan_half_diagonal) * 2.0
    top = local_top(store, eye[0], eye[1], reach_)
    clearance = eye[2] - top
    if not math.isfinite(clearance):
        return max(cap, MIN_NEAR)
    near = 0.5 * clearance / (1.0 + tan_half_diagonal)
    return float(min(max(near, MIN_NEAR), max(cap, MIN_NEAR)))


def reach(store: TerrainStore, eye: tuple[float, float, float]) -> float:
    """An upper bound of the distance from ``eye`` to any terrain of the store: the DEM's
    diagonal, plus the eye's horizontal offset from its centre, plus its height above the
    lowest block."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, _ = zrange(store)
    return (
        math.hypot(x1 - x0, y1 - y0)
        + math.hypot(eye[0] - 0.5 * (x0 + x1), eye[1] - 0.5 * (y0 + y1))
        + abs(eye[2] - zlo)
    )


def fit_clip(store: TerrainStore, camera: Camera) -> Camera:
    """``camera`` with a far plane beyond the whole DEM (1.5 × :func:`reach`) and a near plane
    that follows its clearance (:func:`near_plane`), as ``terrastream render --camera`` uses."""
    eye = (float(camera.position[0]), float(camera.position[1]), float(camera.position[2]))
    r = reach(store, eye)
    near = near_plane(store, eye, camera.tan_half_diagonal, max(0.5, r * 1e-4))
    return dataclasses.replace(camera, near=near, far=max(1.5 * r, 2.0 * near))
