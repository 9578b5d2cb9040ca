"""Fast per-frame needed levels: the patch errors of many blocks kept in slot arrays (pure).

The reference selection (``select_many`` in ``tests/streamer/lod_reference.py``) returns every
leaf node; a streamer only needs each block's needed level, every frame, for many blocks.
:class:`PatchErrorTable` keeps, per refinable depth
``d`` (``d + patch_log2 < k``), the max stored error of each depth-``d`` node's descendants at
depth ``d + patch_log2`` (the error of drawing that node as a patch), for every block that has
its errors, in one ``(slots, 2**d, 2**d)`` float32 array. A frame's levels are then one
vectorised breadth-first pass per depth over all blocks' nodes, with no per-block Python work.
The result equals ``select_many(..., polygon=None)``'s ``needed_level`` (tested).
"""

from __future__ import annotations

import threading
from collections.abc import KeysView, Sequence
from functools import cache, lru_cache
from itertools import repeat
from types import ModuleType

import numpy as np

from streamer.camera import Camera
from streamer.errors import LodError
from streamer.lod import Metric, check_finite_tau, gap_scale, get_metric, horizontal_px, qiu_eq7
from tiler.errors import KernelUnavailableError
from tiler.grid import BlockGrid
from tiler.kernels import ENV, requested
from tiler.quadtree import (
    block_origins,
    half_diagonal,
    max_pool,
    node_centres_at,
    sphere_radius,
    split_children,
)

Block = tuple[int, int]
_READY: list[bool] = []  # set once the compiled kernel has run in this process


@cache
def _load_numba() -> ModuleType | None:
    try:
        from streamer import _plan_nb
    except ImportError:
        return None
    return _plan_nb


def kernels(load: bool = False) -> ModuleType | None:
    """The compiled needed-level kernel (``qiu`` metric) or ``None`` for the numpy reference,
    by ``TERRASTREAM_KERNELS``: ``numpy`` never, ``numba`` always (an error without numba),
    ``auto`` only once :func:`warm_up` has loaded it (or with ``load``), so a session's caller
    never waits for numba's import or a compilation."""
    name = requested()
    if name == "numpy":
        return None
    if name == "auto" and not load and not _READY:
        return None
    mod = _load_numba()
    if mod is None and name == "numba":
        raise KernelUnavailableError(
            f"{ENV}=numba but numba cannot be imported; install the 'fast' extra or unset it."
        )
    return mod


def warm_up(table: PatchErrorTable) -> bool:
    """Import numba and load (or compile) the needed-level kernel for ``table``'s depth count
    (e.g. on a session's planning thread); returns whether it is available."""
    mod = kernels(load=True)
    if mod is None or table.depths == 0:
        return False
    e = np.zeros(0)
    i = np.zeros(0, np.int64)
    arrays = tuple(table._arrays)
    sp = np.ones(table.depths)
    eye, fwd = np.zeros(3), np.zeros(3)
    fwd.flags.writeable = False  # as Camera.forward: the same compiled specialisation
    mod.qiu_levels(arrays, i, e, e, np.zeros((0, 2)), sp, 1, 1, 1.0, sp, sp, eye, fwd, 1.0, 1.0,
                   i, e)  # fmt: skip
    _READY.append(True)
    return True


class PatchErrorTable:
    """Pooled patch errors of blocks, addressable by block, growing as blocks are added.

    One writer at a time (:meth:`add` and :meth:`remove` take the table's own lock) and any
    number of lock-free readers: a block's rows are filled before the block is published, and
    growing copies the arrays (readers keep the list they started with).
    """

    def __init__(self, k: int, patch_log2: int, capacity: int = 64, *, gaps: bool = False) -> None:
        """``gaps``: also hold each block's gap widths (the nodata rule ``"gap"``, see
        :meth:`add` and :meth:`needed_levels`)."""
        if patch_log2 < 0:
            raise LodError(f"patch_log2 must be >= 0, got {patch_log2}")
        self.k = k
        self.patch_log2 = patch_log2
        self.depths = max(0, k - patch_log2)  # refinable depths 0..depths-1
        self._cap = max(1, capacity)
        self._arrays = [
            np.zeros((self._cap, 1 << d, 1 << d), np.float32) for d in range(self.depths)
        ]
        self.gaps = gaps
        self._gap_arrays = [np.zeros_like(a) for a in self._arrays] if gaps else []
        self._has_gap = np.zeros(self._cap, bool)  # per slot: any gap width > 0
        self._slot: dict[Block, int] = {}
        self._free: list[int] = list(range(self._cap - 1, -1, -1))
        self._write = threading.Lock()

    def __contains__(self, block: Block) -> bool:
        return block in self._slot

    def __len__(self) -> int:
        return len(self._slot)

    def add(
        self,
        block: Block,
        field: Sequence[np.ndarray],
        gaps: Sequence[np.ndarray] | None = None,
    ) -> None:
        """Store a block's unpacked error field (one array per depth ``0..k-1``) and, in a
        table made with ``gaps``, its gap widths (:func:`streamer.nodata.gap_widths`, the same
        depths; ``None``: no mask boundary), pooled alike."""
        if len(field) != self.k:
            raise LodError(f"field must hold {self.k} depths, got {len(field)}")
        if gaps is not None and (not self.gaps or len(gaps) != self.k):
            raise LodError(
                f"gap widths need a table made with gaps=True and {self.k} depths "
                f"(this one: gaps={self.gaps}, given {len(gaps)})"
            )
        block = (int(block[0]), int(block[1]))
        pooled = self._pooled(field)
        pooled_gaps = None if gaps is None else self._pooled(gaps)
        with self._write:
            if block in self._slot:
                return
            if not self._free:
                self._grow()
            s = self._free.pop()
            for d in range(self.depths):
                self._arrays[d][s] = pooled[d]
                if self.gaps:
                    self._gap_arrays[d][s] = 0.0 if pooled_gaps is None else pooled_gaps[d]
            self._has_gap[s] = pooled_gaps is not None and any(g.any() for g in pooled_gaps)
            self._slot[block] = s  # published last: readers never see a half-filled slot

    def _pooled(self, field: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Per refinable depth ``d`` the max of ``field`` over each node's depth-``d + p``
        descendants (``(2**d, 2**d)`` float32)."""
        p = self.patch_log2
        pooled = []
        for d in range(self.depths):
            src = np.asarray(field[d + p], dtype=np.float32)
            n, nd = src.shape[0], 1 << d
            if n >= nd:
                pooled.append(max_pool(src, n // nd))
            else:  # stored at a coarser resolution (beyond the cap): repeat
                pooled.append(np.repeat(np.repeat(src, nd // n, axis=0), nd // n, axis=1))
        return pooled

    def remove(self, block: Block) -> None:
        """Forget a block (its slot is reused)."""
        with self._write:
            s = self._slot.pop((int(block[0]), int(block[1])), None)
            if s is not None:
                self._free.append(s)

    def slots(self, blocks: Sequence[Block] | np.ndarray) -> np.ndarray:
        """Slot of each block (``LodError`` for a block whose errors were never added)."""
        if isinstance(blocks, np.ndarray):
            blocks = [tuple(b) for b in blocks.reshape(-1, 2).tolist()]
        arr = self.lookup(blocks)
        if (arr < 0).any():
            b = blocks[int(np.argmin(arr))]
            raise LodError(f"block {tuple(b)} has no errors in the patch table")
        return arr

    def lookup(self, blocks: Sequence[Block]) -> np.ndarray:
        """Slot of each block, -1 where its errors are not in the table (one pass in C for
        tuples, which may hold numpy ints: they hash and compare as the ints do)."""
        get, m = self._slot.get, len(blocks)
        try:
            return np.fromiter(map(get, blocks, repeat(-1)), np.int64, count=m)
        except TypeError:  # unhashable blocks (lists, array rows): as tuples of ints
            keys = [(int(b[0]), int(b[1])) for b in blocks]
            return np.fromiter(map(get, keys, repeat(-1)), np.int64, count=m)

    def delta(
        self, slots: np.ndarray, depth: int, rows: np.ndarray, cols: np.ndarray
    ) -> np.ndarray:
        """Patch errors (float64) of nodes ``(depth, rows, cols)`` of the blocks in ``slots``;
        0 at full resolution (``depth + patch_log2 >= k``)."""
        return _delta(self._arrays, self.depths, slots, depth, rows, cols)

    def known(self, blocks: Sequence[Block]) -> list[Block]:
        """The ``blocks`` (tuples) whose errors are in the table, in their order."""
        slot = self._slot
        return [b for b in blocks if b in slot]

    def keys(self) -> KeysView[Block]:
        """A live view of the blocks in the table (``b in table.keys()`` is ``b in table``
        without a Python call per test: for per-block loops)."""
        return self._slot.keys()

    def depth_array(self, depth: int) -> np.ndarray | None:
        """The ``(slots, 2**depth, 2**depth)`` float32 errors of depth ``depth`` (what
        :meth:`delta` indexes), ``None`` at full resolution (``depth >= depths``: 0 there)."""
        return self._arrays[depth] if depth < self.depths else None

    def _grow(self) -> None:
        old = self._cap
        self._cap *= 2
        self._arrays = [  # new arrays: readers holding the old list stay consistent
            np.concatenate([a, np.zeros((old, *a.shape[1:]), np.float32)]) for a in self._arrays
        ]
        self._gap_arrays = [
            np.concatenate([a, np.zeros((old, *a.shape[1:]), np.float32)]) for a in self._gap_arrays
        ]
        self._has_gap = np.concatenate([self._has_gap, np.zeros(old, bool)])
        self._free.extend(range(self._cap - 1, old - 1, -1))

    def needed_levels(
        self,
        grid: BlockGrid,
        blocks: Sequence[Block],
        camera: Camera,
        tau: float,
        metric: str | Metric,
        zranges: np.ndarray,
        *,
        with_rho: bool = True,
        ids: np.ndarray | None = None,
        slots: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Needed level of each block (all must be in the table) and its largest screen error
        (zeros when ``with_rho`` is False: a caller that only needs levels skips that work);
        ``ids``, if given, is ``blocks`` as an ``(m, 2)`` int64 array, and ``slots`` their
        :meth:`slots` (every one >= 0). In a table with gap
        widths a node also splits while its widest mixed cell can project to more than
        ``min(tau, 1)`` px (:func:`streamer.lod.horizontal_px` of its sphere: the selection's
        rule, ``render.select.select_patches`` with ``gaps``); those blocks take the numpy walk."""
        fn = get_metric(metric)
        tau = check_finite_tau(tau)  # inf: mixed nodes (error inf) would not split
        k, p = self.k, self.patch_log2
        m = len(blocks)
        levels = np.full(m, min(k, p), dtype=np.int64)
        rho_max = np.zeros(m)
        if m == 0 or self.depths == 0:
            return levels, rho_max
        blk = np.asarray(blocks, dtype=np.int64).reshape(-1, 2) if ids is None else ids
        slots = self.slots(blocks) if slots is None else slots
        arrays = self._arrays  # after the slots: it holds every slot published before them
        gap_arrays, has_gap = self._gap_arrays, self._has_gap  # (likewise)
        zr = np.asarray(zranges, dtype=np.float64).reshape(m, 2)
        gapped = has_gap[slots] if self.gaps and tau > 0 else np.zeros(m, bool)
        plain = np.flatnonzero(~gapped)
        nb = kernels() if fn is qiu_eq7 else None
        if nb is not None and len(plain):  # the compiled walk: the same levels and errors
            every = len(plain) == m  # (no block with gap widths: no copies)
            sub, zp, ip = (slots, zr, blk) if every else (slots[plain], zr[plain], blk[plain])
            lv, rh = (levels, rho_max) if every else (levels[plain], rho_max[plain])
            bx0, by1 = block_origins(grid, ip[:, 0], ip[:, 1])
            hd, sdx, sdy = _depth_geometry(grid, self.depths)
            nb.qiu_levels(
                tuple(arrays), sub, bx0, by1, np.ascontiguousarray(zp), hd, k, p, float(tau),
                sdx, sdy, camera.eye, camera.forward, float(camera.focal_px),
                float(camera.near), lv, rh,
            )  # fmt: skip
            if not every:
                levels[plain], rho_max[plain] = lv, rh
        elif len(plain):
            walk = (grid, blk, slots, arrays, None, zr, camera, tau, fn, with_rho)
            self._walk(*walk, plain, levels, rho_max)
        if gapped.any():
            walk = (grid, blk, slots, arrays, gap_arrays, zr, camera, tau, fn, with_rho)
            self._walk(*walk, np.flatnonzero(gapped), levels, rho_max)
        return levels, (rho_max if with_rho else np.zeros(m))

    def _walk(
        self,
        grid: BlockGrid,
        blk: np.ndarray,
        slots: np.ndarray,
        arrays: list[np.ndarray],
        gap_arrays: list[np.ndarray] | None,
        zr: np.ndarray,
        camera: Camera,
        tau: float,
        fn: Metric,
        with_rho: bool,
        idx: np.ndarray,
        levels: np.ndarray,
        rho_max: np.ndarray,
    ) -> None:
        """The numpy walk of :meth:`needed_levels` over the blocks ``idx``, into ``levels`` and
        ``rho_max``; with ``gap_arrays`` the gap rule's split too."""
        k, p = self.k, self.patch_log2
        zmid, zhalf = 0.5 * (zr[:, 0] + zr[:, 1]), 0.5 * (zr[:, 1] - zr[:, 0])
        bx0, by1 = block_origins(grid, blk[:, 0], blk[:, 1])
        scale = gap_scale(tau)
        rows = np.zeros(len(idx), dtype=np.int64)
        cols = np.zeros(len(idx), dtype=np.int64)
        for d in range(self.depths):
            levels[idx] = d + p  # every block still holding nodes reaches this depth
            delta = _delta(arrays, self.depths, slots[idx], d, rows, cols)
            cx, cy = node_centres_at(grid, bx0[idx], by1[idx], d, rows, cols)
            centres = np.stack([cx, cy, zmid[idx]], axis=1)
            radius = sphere_radius(half_diagonal(grid, d), zhalf[idx])
            rho = np.asarray(fn(delta, centres, radius, camera))
            if gap_arrays is not None:
                w = _delta(gap_arrays, self.depths, slots[idx], d, rows, cols)
                if (w > 0).any():  # rho > tau also when the gap projects past min(tau, 1) px
                    g = np.asarray(horizontal_px(w, centres, radius, camera), np.float64)
                    rho = np.maximum(rho, g * scale)
            if with_rho:
                np.maximum.at(rho_max, idx, np.where(np.isfinite(rho), rho, 1e30))
            split = ~(rho <= tau)
            if not split.any():
                break
            idx, rows, cols = split_children(idx, rows, cols, split)
        else:
            levels[idx] = k  # nodes split down to full resolution


@lru_cache(maxsize=16)
def _depth_geometry(grid: BlockGrid, depths: int) -> tuple[np.ndarray, ...]:
    """Per depth: the node half diagonal and the node span times ``dx`` and ``dy`` (the
    reference's ``half_diagonal`` and ``node_centres_at`` factors, computed once per grid;
    shared between calls, never written)."""
    spans = [float(1 << (grid.k - d)) for d in range(depths)]
    return (
        np.array([half_diagonal(grid, d) for d in range(depths)]),
        np.array([s * grid.dx for s in spans]),
        np.array([s * grid.dy for s in spans]),
    )


def _delta(
    arrays: list[np.ndarray],
    depths: int,
    slots: np.ndarray,
    depth: int,
    rows: np.ndarray,
    cols: np.ndarray,
) -> np.ndarray:
    if depth >= depths:
        return np.zeros(len(slots))
    return arrays[depth][slots, rows, cols].astype(np.float64)
