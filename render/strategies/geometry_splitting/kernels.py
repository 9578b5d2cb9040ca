"""``geometry-splitting``'s compiled kernels, chosen like :mod:`tiler.kernels`: numba when it is
installed (the ``fast`` extra), the numpy reference otherwise. ``TERRASTREAM_KERNELS``
(``auto``, ``numba``, ``numpy``) or the ``kernels`` argument picks the backend; ``auto`` uses
numba only after :func:`warm_up` (a one-shot command never waits for it)."""

from __future__ import annotations

from collections.abc import Iterable
from functools import cache
from types import ModuleType

import numpy as np

from render.strategies.geometry_splitting import pure
from render.strategies.geometry_splitting.pure import BlockTree
from render.strategies.geometry_splitting.pure import quad_errors as quad_errors_numpy
from tiler.kernels import pick_warm, requested, warm

_READY: list[bool] = []  # filled by warm_up(): ``auto`` may use the compiled kernel


@cache
def _load_numba() -> ModuleType | None:
    try:
        from render.strategies.geometry_splitting import _tree_nb
    except ImportError:
        return None
    return _tree_nb


def resolve(kernels: str | None = None) -> ModuleType | None:
    """The numba kernel module for backend ``kernels`` (default: ``TERRASTREAM_KERNELS``), or
    ``None`` for the numpy reference; ``auto`` only after :func:`warm_up`."""
    return pick_warm(kernels, _load_numba, _READY)


def warm_up() -> bool:
    """Import numba and the kernels now and call each once on a 3² grid, which loads them from
    numba's cache (or compiles them) here rather than on the render thread at the first tree
    it builds (~80 ms); only then does ``auto`` use them (a thread that called them while this
    one loads them would wait for numba's compiler lock). Whether they are available."""
    mod = None if requested() == "numpy" else _load_numba()
    if mod is not None:
        g = np.zeros((3, 3))
        mod.quad_errors_depth(g, np.ones((3, 3), bool), 0, np.empty((1, 1)))
        mod.corner_ranges(g, 2, np.zeros((1, 1)), np.empty((1, 1)), np.empty((1, 1)))
    return warm(_load_numba, _READY)


def quad_errors(
    h: np.ndarray, valid: np.ndarray | None, depths: Iterable[int], kernels: str | None = None
) -> dict[int, np.ndarray]:
    """:func:`render.strategies.geometry_splitting.pure.quad_errors` (the same values) by the
    backend ``kernels`` picks: 1025² blocks, depths 7–9, ~35 ms in numpy."""
    mod = resolve(kernels)
    if mod is None:
        return quad_errors_numpy(h, valid, depths)
    g = np.ascontiguousarray(h, dtype=np.float64)
    # writable, as warm_up's: a session's read-only mask would be another signature to load
    ok = np.ones(g.shape, bool) if valid is None else np.require(valid, bool, ["C", "W"])
    out = {}
    for d in depths:
        out[d] = np.empty((1 << d, 1 << d))
        mod.quad_errors_depth(g, ok, d, out[d])
    return out


def _corners(mod: ModuleType):
    def corners(g: np.ndarray, step: int, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = delta.shape[0]
        lo, hi = np.empty((m, m)), np.empty((m, m))
        mod.corner_ranges(np.ascontiguousarray(g), step, np.ascontiguousarray(delta), lo, hi)
        return lo, hi

    return corners


def packed_tree(
    bound: list[np.ndarray],
    grid: np.ndarray,
    mixed: list[np.ndarray] | None = None,
    kernels: str | None = None,
    depth: int | None = None,
) -> np.ndarray:
    """:func:`render.strategies.geometry_splitting.pure.packed_tree` (the same bytes), its
    corner ranges by the compiled kernel when the backend ``kernels`` picks is numba."""
    mod = resolve(kernels)
    if mod is None:
        return pure.packed_tree(bound, grid, mixed, depth=depth)
    return pure.packed_tree(bound, grid, mixed, _corners(mod), depth=depth)


def stored_tree(
    bound: list[np.ndarray],
    grid: np.ndarray,
    exact: dict[int, np.ndarray] | None = None,
    kernels: str | None = None,
) -> BlockTree:
    """:func:`render.strategies.geometry_splitting.pure.stored_tree` (the same arrays), its
    corner ranges by the compiled kernel when the backend ``kernels`` picks is numba (1025²
    at full resolution: ~6 ms of its ~11 in numpy)."""
    mod = resolve(kernels)
    if mod is None:
        return pure.stored_tree(bound, grid, exact)
    return pure.stored_tree(bound, grid, exact, _corners(mod))
