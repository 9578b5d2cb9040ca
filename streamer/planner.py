"""Which blocks, at which levels, for which pose (pure: no threads, no I/O).

A :class:`Planner` answers two questions for a camera pose:

* :meth:`Planner.needed` — the visible set ``M`` (Qiu's projected triangle, or Jung & Han's
  hull) and the level each of its blocks needs to be drawn at ``tau``;
* :meth:`Planner.prefetch` — the blocks ``N`` of the frustum extension (of this pose and of the
  pose ``horizon_s`` ahead along the velocity) and the level each would need at
  ``tau * lookahead``, with its screen error as priority.

``SessionConfig.scheme`` picks which of these are on (:data:`streamer.frames.SCHEMES`): under
``"qiu"`` (Qiu et al. as published) ``N`` is the extension of this pose only and every block is
planned at the level it needs at ``tau``; the pose ahead and the ``lookahead`` factor are this
project's additions.

Blocks whose static errors are not known yet need the patch level (``patch_log2``). The error
table is read lock-free (see :class:`streamer.levels.PatchErrorTable`), so planning holds no
lock the loaders take.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, replace
from itertools import chain

import numpy as np

from streamer.cache import Block
from streamer.camera import Camera
from streamer.frames import SessionConfig
from streamer.frustum import (
    as_polygon,
    block_edge,
    blocks_meeting,
    candidate_window,
    extension_triangle,
    frustum_hull,
    view_triangle,
)
from streamer.levels import PatchErrorTable
from streamer.levels import kernels as plan_kernels
from streamer.restriction import restrict_levels
from tiler.grid import BlockGrid
from tiler.quadtree import block_zranges


def _blocks_meeting_nb(nb, polygon: np.ndarray, grid: BlockGrid, exists: np.ndarray) -> np.ndarray:
    """``blocks_meeting(polygon, grid)`` restricted to ``exists``, the per-block test compiled
    (``nb``: :mod:`streamer._plan_nb`); the polygon's part is the reference's numpy code."""
    poly = as_polygon(polygon)
    win = candidate_window(poly, grid)
    if win is None:
        return np.zeros((0, 2), dtype=np.int64)
    r0, r1, c0, c1 = win
    o = poly[0]
    p = poly - o
    # the reference's numpy steps on a handful of vertices, as float operations (the same
    # bits: differences, negations, min and max are exact); the projections stay numpy's
    pts = p.tolist()
    xs, ys = [q[0] for q in pts], [q[1] for q in pts]
    pbox = np.array([min(xs), max(xs), min(ys), max(ys)])
    n = len(pts)
    if n >= 2:
        nxt = pts[1:] + pts[:1]  # np.roll(p, -1, axis=0)
        normals = np.array([[-(b[1] - a[1]), b[0] - a[0]] for a, b in zip(pts, nxt, strict=True)])
        proj = p @ normals.T
        pmin, pmax = proj.min(axis=0), proj.max(axis=0)
    else:
        normals, pmin, pmax = np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    return nb.blocks_meeting(
        r0, r1, c0, c1, float(grid.x0), float(grid.y0), int(grid.step), float(grid.dx),
        float(grid.dy), o, pbox, np.ascontiguousarray(normals), pmin, pmax, exists,
    )  # fmt: skip


@dataclass(frozen=True)
class PrefetchPlan:
    """Blocks to hold ahead of time: ``wants[b] = (level, screen error)``; ``ring`` = |N - M|."""

    wants: dict[Block, tuple[int, float]]
    ring: int


class Planner:
    """Visible and prefetch sets and their levels for a store's grid (see module doc)."""

    def __init__(
        self,
        grid: BlockGrid,
        k: int,
        exists: np.ndarray,
        zmin: np.ndarray,
        zmax: np.ndarray,
        errors: PatchErrorTable,
        config: SessionConfig,
    ) -> None:
        self.grid = grid
        self.k = k
        self.exists = np.asarray(exists, dtype=bool)
        self.zr = block_zranges(zmin, zmax)
        ok = self.exists & np.isfinite(zmin) & np.isfinite(zmax)
        lo = float(np.min(np.asarray(zmin)[ok])) if ok.any() else 0.0
        hi = float(np.max(np.asarray(zmax)[ok])) if ok.any() else 0.0
        self.zrange = (lo, hi)
        self.errors = errors
        self.config = config

    def _existing_ids(self, polygon: np.ndarray) -> np.ndarray:
        nb = plan_kernels()
        if nb is not None:  # the compiled test: the same blocks (tested)
            return _blocks_meeting_nb(nb, polygon, self.grid, self.exists)
        ids = blocks_meeting(polygon, self.grid)
        return ids[self.exists[ids[:, 0], ids[:, 1]]]

    def _existing(self, polygon: np.ndarray) -> list[Block]:
        return _tuples(self._existing_ids(polygon))

    def _visible_ids(self, camera: Camera, culling: str | None) -> np.ndarray:
        if (culling or self.config.culling) == "qiu":
            return self._existing_ids(view_triangle(camera, zrange=self.zrange))
        return self._existing_ids(frustum_hull(camera, self.zrange))

    def visible(self, camera: Camera, culling: str | None = None) -> list[Block]:
        """Blocks meeting the projected frustum: Qiu's triangle (``culling="qiu"``) or Jung &
        Han's hull (``"hull"``); default the session's culling."""
        return _tuples(self._visible_ids(camera, culling))

    def levels(
        self,
        camera: Camera,
        blocks: list[Block],
        tau: float,
        *,
        with_rho: bool = True,
        ids: np.ndarray | None = None,
    ) -> tuple[dict[Block, int], dict[Block, float]]:
        """Needed level and largest screen error of each block at ``tau`` (patch level and 0
        for blocks whose errors are not known yet; without ``with_rho`` the errors are not
        computed and the second mapping is empty). ``ids``: ``blocks`` as an ``(m, 2)`` array,
        if the caller has it (saves converting them back)."""
        if ids is None:
            ids = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
        lv, r = self._level_arrays(camera, blocks, ids, tau, with_rho)
        needed = dict(zip(blocks, lv.tolist(), strict=True))
        return needed, (dict(zip(blocks, r.tolist(), strict=True)) if with_rho else {})

    def _restrict(self, ids: np.ndarray, levels: np.ndarray) -> np.ndarray:
        """:func:`streamer.restriction.restrict_levels` at the session's patch size (compiled
        when the planning kernels are)."""
        return restrict_levels(ids, levels, self.config.patch_log2, plan_kernels())

    def _level_arrays(
        self, camera: Camera, blocks: list[Block], ids: np.ndarray, tau: float, with_rho: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`levels` as arrays in the order of ``blocks`` (``ids``: the same as rows):
        one lookup of every block's slot, the compiled walk over the known ones, the
        neighbour restriction over all of them."""
        m = len(blocks)
        slots = self.errors.lookup(blocks)
        known = slots >= 0
        levels = np.full(m, min(self.config.patch_log2, self.k), dtype=np.int64)
        rho = np.zeros(m)
        if m == 0 or not known.any():
            return levels, rho  # no errors yet: the patch level
        idx = None if known.all() else np.flatnonzero(known)
        have = blocks if idx is None else [blocks[i] for i in idx.tolist()]
        sub = ids if idx is None else ids[idx]
        lv, r = self.errors.needed_levels(
            self.grid, have, camera, tau, self.config.metric, self.zr[sub[:, 0], sub[:, 1]],
            with_rho=with_rho, ids=sub, slots=slots if idx is None else slots[idx],
        )  # fmt: skip
        if idx is None:
            return self._restrict(ids, lv), r
        levels[idx], rho[idx] = lv, r
        return (self._restrict(ids, levels) if m >= 2 else levels), rho

    def needed(
        self, camera: Camera, tau: float | None = None, culling: str | None = None
    ) -> dict[Block, int]:
        """The visible blocks and the level each needs to be drawn at ``tau``."""
        blocks, levels = self.needed_arrays(camera, tau, culling)
        return dict(zip(blocks, levels.tolist(), strict=True))

    def needed_arrays(
        self, camera: Camera, tau: float | None = None, culling: str | None = None
    ) -> tuple[list[Block], np.ndarray]:
        """:meth:`needed` as the visible blocks (row-major) and their levels (int64), for a
        caller that works on arrays."""
        t = self.config.tau if tau is None else tau
        ids = self._visible_ids(camera, culling)
        blocks = _tuples(ids)
        return blocks, self._level_arrays(camera, blocks, ids, t, False)[0]

    def poses(self, camera: Camera, velocity: np.ndarray | None) -> list[Camera]:
        """This pose and, when moving, the pose ``horizon_s`` ahead along ``velocity`` (only
        under a scheme with pose-ahead, see :data:`streamer.frames.SCHEMES`)."""
        out = [camera]
        cfg = self.config
        v = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64)
        if cfg.prefetch and cfg.plan_horizon_s > 0 and np.any(v):
            ahead = np.asarray(camera.position, dtype=np.float64) + v * cfg.plan_horizon_s
            out.append(replace(camera, position=tuple(ahead.tolist())))
        return out

    def prefetch(
        self,
        camera: Camera,
        velocity: np.ndarray | None,
        visible: Collection[Block],
        tau: float | None = None,
    ) -> PrefetchPlan:
        """The blocks ``N`` (``visible`` plus the extension) and the level each would need at
        ``tau * lookahead`` from either pose (see module doc)."""
        cfg = self.config
        t = cfg.tau if tau is None else tau
        poses = self.poses(camera, velocity)
        parts = [_ids_of(visible)]
        if cfg.prefetch:
            v = np.zeros(3) if velocity is None else np.asarray(velocity, dtype=np.float64)
            edge = block_edge(self.grid) if cfg.extension_L is None else cfg.extension_L
            for cam in poses:
                poly = extension_triangle(cam, edge, velocity=v, fps=cfg.fps)
                parts.append(self._existing_ids(poly))
        ids = _union_sorted(np.concatenate(parts), self.grid.cols)  # sorted(set(N)), as rows
        blocks = _tuples(ids)
        m = len(blocks)
        slots = self.errors.lookup(blocks)
        known = slots >= 0
        if not known.any():
            wants = dict.fromkeys(blocks, (0, 0.0))
            return PrefetchPlan(wants=wants, ring=m - len(visible))
        idx = None if known.all() else np.flatnonzero(known)
        have = blocks if idx is None else [blocks[i] for i in idx.tolist()]
        sub = ids if idx is None else ids[idx]
        sub_slots = slots if idx is None else slots[idx]
        t_ahead = t * (cfg.plan_lookahead if cfg.prefetch else 1.0)
        zr = self.zr[sub[:, 0], sub[:, 1]]
        lv = np.zeros(len(have), dtype=np.int64)
        rh = np.zeros(len(have))
        for cam in poses:
            a, r = self.errors.needed_levels(
                self.grid, have, cam, t_ahead, cfg.metric, zr, ids=sub, slots=sub_slots
            )
            np.maximum(lv, a, out=lv)
            np.maximum(rh, r, out=rh)
        levels, rho = (lv, rh) if idx is None else (np.zeros(m, np.int64), np.zeros(m))
        if idx is not None:  # blocks without errors: level 0, no priority
            levels[idx], rho[idx] = lv, rh
        if m >= 2:  # raised where a neighbour is too fine for stitching to join
            levels = self._restrict(ids, levels)
        wants = dict(zip(blocks, zip(levels.tolist(), rho.tolist(), strict=True), strict=True))
        return PrefetchPlan(wants=wants, ring=m - len(visible))


def _tuples(ids: np.ndarray) -> list[Block]:
    """``(m, 2)`` block rows as tuples of ints (no list per row: fewer objects for the
    collector to count)."""
    return list(zip(ids[:, 0].tolist(), ids[:, 1].tolist(), strict=True))


def _ids_of(blocks: Collection[Block]) -> np.ndarray:
    """Blocks as an ``(m, 2)`` int64 array (one pass in C over the tuples)."""
    m = len(blocks)
    return np.fromiter(chain.from_iterable(blocks), np.int64, count=2 * m).reshape(m, 2)


def _union_sorted(ids: np.ndarray, cols: int) -> np.ndarray:
    """The distinct rows of ``ids``, in the order ``sorted`` gives their tuples."""
    if len(ids) == 0:
        return ids.reshape(0, 2)
    r, c = ids[:, 0], ids[:, 1]
    if c.min() >= 0 and c.max() < cols and r.min() >= 0:  # row-major numbers sort alike
        flat = np.unique(r * cols + c)
        return np.stack([flat // cols, flat % cols], axis=1)
    return np.unique(ids, axis=0)
