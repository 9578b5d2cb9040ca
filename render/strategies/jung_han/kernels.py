"""``jung-han``'s compiled selection kernels, chosen like :mod:`tiler.kernels`: numba when it is
installed (the ``fast`` extra), the numpy reference otherwise. ``TERRASTREAM_KERNELS`` (``auto``,
``numba``, ``numpy``) or the selector's ``kernels`` argument picks the backend; ``auto`` uses
numba only after :func:`warm_up` (a one-shot command never waits for it; importing this module
costs nothing).

:class:`Forest` holds the cached trees' heights, δ and pyramids in flat arrays, copying in only
the trees built or rebuilt since the last frame (each frame then picks its blocks' offsets)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from types import ModuleType

import numpy as np

from render.strategies.jung_han.pure import Block, BlockTree, grid_level, index_positions
from tiler.kernels import pick_warm, requested, warm


@cache
def _load_numba() -> ModuleType | None:
    try:
        from render.strategies.jung_han import _kernels_nb
    except ImportError:
        return None
    return _kernels_nb


_READY: list[bool] = []  # filled by warm_up(): ``auto`` may use the compiled kernels


def resolve(kernels: str | None = None) -> ModuleType | None:
    """The numba kernel module for backend ``kernels`` (default: ``TERRASTREAM_KERNELS``), or
    ``None`` for the numpy reference; ``auto`` only after :func:`warm_up`."""
    return pick_warm(kernels, _load_numba, _READY)


def warm_up(run: Callable[[], object] | None = None) -> bool:
    """Import numba and jung-han's kernels now, after which ``auto`` uses them; ``run``
    (:func:`render.strategies.jung_han.warm.warm_up_selection`) calls them once first, so
    they load from numba's cache (or compile) here and not in the render thread's first
    compiled selection (~80 ms). Whether they are available."""
    if run is not None and requested() != "numpy" and _load_numba() is not None:
        run()
    return warm(_load_numba, _READY)


@cache
def _perms(rr: int) -> np.ndarray:
    """``pure.index_positions`` of depths ``0 .. rr - 1`` concatenated (depth ``d`` at
    ``(4**d - 1) // 3``)."""
    return np.concatenate([index_positions(d) for d in range(rr)] or [np.zeros(0)]).astype(np.int64)


def build_tree(mod: ModuleType, heights: np.ndarray) -> BlockTree:
    """``BlockTree.build(heights)`` by the compiled kernel of ``mod`` (the same values)."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    rr = grid_level(h.shape)
    delta, dmax, zlo, zhi = mod.build_tree(h, _perms(rr))
    at = [((1 << (2 * d)) - 1) // 3 for d in range(rr + 1)]

    def split(a: np.ndarray) -> list[np.ndarray]:
        return [a[at[d] : at[d + 1]] for d in range(rr)]

    return BlockTree(rr, h, delta, split(dmax), split(zlo), split(zhi))


@dataclass
class _Placed:
    """Where one cached tree lies in the forest's arrays."""

    tree: BlockTree
    hoff: int
    poff: int


class Forest:
    """The selector's cached trees in flat arrays the compiled kernels read: a tree's heights
    and δ at its ``hoff``, its depth-packed pyramid (depth ``d`` at ``poff + (4**d - 1) //
    3``) at its ``poff``. A tree built or rebuilt is copied into a free region of its size (or
    appended; the arrays grow by doubling); a dropped one frees its regions; the arrays are
    compacted when more than half of their used length is free. So a frame whose blocks
    change level copies those trees only, not the whole forest."""

    #: compaction only past this many free heights (small forests keep their holes)
    MIN_COMPACT = 1 << 18

    def __init__(self) -> None:
        self.heights = np.zeros(0)  # float64
        self.delta = np.zeros(0, np.float32)
        #: ``(dmax, zlo, zhi)`` per packed node, ``(n, 3)`` float64 (``dmax`` widened exactly
        #: from float32): the traversal's bound reads one cache line per node, not three
        self.pyramid = np.zeros((0, 3))
        self._placed: dict[Block, _Placed] = {}
        self._free: dict[tuple[int, int], list[tuple[int, int]]] = {}
        self._hend = self._pend = 0  # used lengths (placed trees and free regions)
        self._hfree = 0  # heights in free regions
        #: trees copied in, and compactions, since creation (tests, benchmarks)
        self.copies = 0
        self.compactions = 0

    @staticmethod
    def _sizes(t: BlockTree) -> tuple[int, int]:
        return int(t.heights.size), int(sum(len(a) for a in t.dmax))

    def sync(self, trees: dict[Block, BlockTree]) -> int:
        """Make the arrays hold exactly ``trees`` (the selector's cache, by block): free the
        regions of dropped or replaced trees, copy in the new ones; returns how many were
        copied."""
        for b in [b for b, p in self._placed.items() if trees.get(b) is not p.tree]:
            p = self._placed.pop(b)
            size = self._sizes(p.tree)
            self._free.setdefault(size, []).append((p.hoff, p.poff))
            self._hfree += size[0]
        new = [(b, t) for b, t in trees.items() if b not in self._placed]
        if len(new) > 1:  # one growth for them all (not one per doubling)
            sizes = [self._sizes(t) for _, t in new]
            self._reserve(
                self._hend + sum(h for h, _ in sizes), self._pend + sum(p for _, p in sizes)
            )
        for b, t in new:
            self._place(b, t)
        if self._hfree > max(self._hend // 2, self.MIN_COMPACT):
            self._compact()
        return len(new)

    def offsets(self, blocks: list[Block]) -> tuple[np.ndarray, np.ndarray]:
        """``(hoff, poff)`` of the trees of ``blocks`` (each placed), as int64 arrays."""
        pl = self._placed
        hoff = np.array([pl[b].hoff for b in blocks], dtype=np.int64)
        poff = np.array([pl[b].poff for b in blocks], dtype=np.int64)
        return hoff, poff

    def _place(self, b: Block, t: BlockTree) -> None:
        size = self._sizes(t)
        spare = self._free.get(size)
        if spare:
            h, p = spare.pop()
            self._hfree -= size[0]
        else:
            h, p = self._hend, self._pend
            self._reserve(h + size[0], p + size[1])
            self._hend, self._pend = h + size[0], p + size[1]
        self._copy(t, h, p, size)
        self._placed[b] = _Placed(t, h, p)

    def _copy(self, t: BlockTree, h: int, p: int, size: tuple[int, int]) -> None:
        nh, npy = size
        self.heights[h : h + nh] = t.heights.ravel()
        self.delta[h : h + nh] = t.delta.ravel()
        for col, arrays in enumerate((t.dmax, t.zlo, t.zhi)):
            at = p
            for a in arrays:
                self.pyramid[at : at + len(a), col] = a
                at += len(a)
        self.copies += 1

    def _reserve(self, nh: int, npy: int) -> None:
        """Grow the arrays (doubling, keeping their used part) to hold ``nh`` heights and
        ``npy`` pyramid nodes."""
        if nh > len(self.heights):
            cap = max(nh, 2 * len(self.heights))
            for name, dt in (("heights", np.float64), ("delta", np.float32)):
                old, arr = getattr(self, name), np.empty(cap, dt)
                arr[: self._hend] = old[: self._hend]
                setattr(self, name, arr)
        if npy > len(self.pyramid):
            arr = np.empty((max(npy, 2 * len(self.pyramid)), 3))
            arr[: self._pend] = self.pyramid[: self._pend]
            self.pyramid = arr

    def _compact(self) -> None:
        """Copy the placed trees into new arrays of their used size, free regions gone."""
        placed = list(self._placed.items())
        nh = sum(self._sizes(p.tree)[0] for _, p in placed)
        npy = sum(self._sizes(p.tree)[1] for _, p in placed)
        old = (self.heights, self.delta, self.pyramid)
        self.heights, self.delta = np.empty(nh), np.empty(nh, np.float32)
        self.pyramid = np.empty((npy, 3))
        h = p = 0
        for b, pl in placed:
            sh, sp = self._sizes(pl.tree)
            self.heights[h : h + sh] = old[0][pl.hoff : pl.hoff + sh]
            self.delta[h : h + sh] = old[1][pl.hoff : pl.hoff + sh]
            self.pyramid[p : p + sp] = old[2][pl.poff : pl.poff + sp]
            self._placed[b] = _Placed(pl.tree, h, p)
            h, p = h + sh, p + sp
        self._hend, self._pend, self._hfree = h, p, 0
        self._free.clear()
        self.compactions += 1
