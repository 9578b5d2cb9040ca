"""``jung-han``'s compiled selection kernels, chosen like :mod:`tiler.kernels`: numba when it is
installed (the ``fast`` extra), the numpy reference otherwise. ``TERRASTREAM_KERNELS`` (``auto``,
``numba``, ``numpy``) or the selector's ``kernels`` argument picks the backend; ``auto`` uses
numba only after :func:`warm_up` (a one-shot command never waits for it; importing this module
costs nothing).

:class:`Forest` packs the cached trees' heights, δ and pyramids into flat arrays, again only
when a tree is built, rebuilt or dropped (each frame then picks its blocks' offsets)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache, cached_property
from types import ModuleType

import numpy as np

from render.strategies.jung_han.pure import BlockTree
from tiler.kernels import pick_warm, warm


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


def warm_up() -> bool:
    """Import numba and jung-han's kernels now, after which ``auto`` uses
    them (they load from numba's cache, or compile, on their first call); whether they are
    available."""
    return warm(_load_numba, _READY)


@dataclass
class Forest:
    """The selector's cached trees, flat: tree ``i``'s heights/δ at ``hoff[i]``, its
    depth-packed pyramids (depth ``d`` at ``poff[i] + (4**d - 1) // 3``) at ``poff[i]``."""

    key: tuple
    heights: np.ndarray
    delta: np.ndarray
    dmax: np.ndarray
    zlo: np.ndarray
    zhi: np.ndarray
    hoff: np.ndarray
    poff: np.ndarray
    #: the packed trees themselves: while the forest lives their ``id`` (in ``key``) is unique
    trees: list = field(repr=False, default_factory=list)

    @cached_property
    def pyramid(self) -> np.ndarray:
        """``(dmax, zlo, zhi)`` per packed node as one ``(n, 3)`` float64 array (``dmax``
        widened exactly): the traversal's bound reads one cache line per node, not three."""
        return np.ascontiguousarray(np.stack([self.dmax.astype(np.float64), self.zlo, self.zhi], 1))

    @cached_property
    def index(self) -> dict:
        """Block -> position of its tree in the packed arrays (``key`` lists ``(block, ...)``)."""
        return {k[0]: i for i, k in enumerate(self.key)}

    @classmethod
    def pack(cls, key: tuple, trees: list[BlockTree]) -> Forest:
        """Concatenate the trees' arrays (in ``key``'s order)."""
        hs = [t.heights.ravel() for t in trees]
        hoff = np.cumsum([0] + [len(h) for h in hs])[:-1].astype(np.int64)
        pyr = [(t.dmax, t.zlo, t.zhi) for t in trees]
        plen = [sum(len(a) for a in p[0]) for p in pyr]
        poff = np.cumsum([0, *plen])[:-1].astype(np.int64)

        def cat(arrays, dtype):
            return np.concatenate([np.asarray(a, dtype) for a in arrays] or [np.zeros(0, dtype)])

        return cls(
            key,
            cat(hs, np.float64),
            cat([t.delta.ravel() for t in trees], np.float32),
            cat([a for p in pyr for a in p[0]], np.float32),
            cat([a for p in pyr for a in p[1]], np.float64),
            cat([a for p in pyr for a in p[2]], np.float64),
            hoff,
            poff,
            list(trees),
        )
