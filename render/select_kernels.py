"""The compiled walk of :func:`render.select.select_patches`, chosen like :mod:`tiler.kernels`:
numba when it is installed (the ``fast`` extra), the numpy reference otherwise;
``TERRASTREAM_KERNELS`` (``auto``, ``numba``, ``numpy``) or ``select_patches(kernels=...)``
picks it. ``auto`` uses the compiled walk only once :func:`warm_up` has loaded it (the viewer
does so on a background thread; the benchmarks before timing), so a one-frame ``render`` never
waits ~1 s for numba's import and cache (importing this module costs nothing). The walk is
the reference's, one depth per step, with the per-node work of a depth in
two kernel calls (:mod:`render._select_nb`); Qiu's metric and Kim's (``chunk-tessellation``,
named by its ``select_kernel`` attribute) are compiled too, any other metric (the conservative
ones, callables, node boxes) is the reference's :func:`render.node_boxes.node_rho`. Same patches,
bit for bit (tests/render/test_select_kernels.py). The stitch's rounds go with the same module
(:func:`stitch_kernels`, :mod:`render.stitch_fast`; tests/render/test_stitch_fast.py)."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from render.node_boxes import NodeBoxes, node_rho
from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from streamer.lod import Metric, horizontal_px, qiu_eq7
from tiler.grid import BlockGrid
from tiler.kernels import pick_warm, requested, warm
from tiler.quadtree import half_diagonal, node_span

if TYPE_CHECKING:
    from render.select import DiscCull

_NONE = np.zeros(0)
_NONE_B = np.zeros(0, np.bool_)


@cache
def _load_numba() -> ModuleType | None:
    try:
        from render import _select_nb
    except ImportError:
        return None
    return _select_nb


@cache
def _load_stitch() -> ModuleType | None:
    try:
        from render import _stitch_nb
    except ImportError:
        return None
    return _stitch_nb


def stitch_kernels(nb: ModuleType | None) -> ModuleType | None:
    """The compiled stitch rounds (:mod:`render._stitch_nb`) that go with the kernel module
    ``nb`` from :func:`resolve`: only with the real one (a stand-in module, as the tests'
    faulty kernels, gets the reference rounds over its own neighbour search)."""
    return _load_stitch() if nb is not None and nb is _load_numba() else None


_READY: list[bool] = []  # filled by warm_up(): ``auto`` may use the compiled walk


def resolve(kernels: str | None = None) -> ModuleType | None:
    """The numba kernel module for backend ``kernels`` (default: ``TERRASTREAM_KERNELS``), or
    ``None`` for the numpy reference; ``auto`` only after :func:`warm_up`."""
    return pick_warm(kernels, _load_numba, _READY)


def warm_up(run: Callable[[], object] | None = None) -> bool:
    """Import numba and the compiled walk now, after which ``auto`` uses it; first the
    stitch's kernels are loaded (:func:`render.stitch_fast.warm_up`) and ``run``
    (:func:`render.select_warm.warm_up_walk`) calls the walk's, so they load from numba's cache
    (or compile) here and not in the render thread's first compiled selection (~12 ms), nor
    while it waits for numba's lock. Whether it is available."""
    if requested() != "numpy" and _load_numba() is not None:
        kn = stitch_kernels(_load_numba())
        if kn is not None:
            from render import stitch_fast

            stitch_fast.warm_up(kn)
        if run is not None:
            run()
    return warm(_load_numba, _READY)


def walk(
    nb: ModuleType,
    grid: BlockGrid,
    table: PatchErrorTable,
    slots: np.ndarray,
    fn: Metric,
    camera: Camera,
    tau: float,
    *,
    idx: np.ndarray,
    res: np.ndarray,
    zr: np.ndarray,
    win: np.ndarray | None,
    bx0: np.ndarray,
    by1: np.ndarray,
    cull: DiscCull | None,
    min_depth: int,
    boxes: NodeBoxes | None,
    box_slots: tuple[np.ndarray, np.ndarray] | None,
    gap: tuple[PatchErrorTable, np.ndarray, float] | None = None,
) -> tuple[list[tuple], int]:
    """``select_patches``' per-depth leaves ``(idx, depth, rows, cols, level, delta, rho)`` and
    its clamped count, from the kernels of ``nb`` (``cull`` a :class:`render.select.DiscCull`
    or None, ``win`` None when no node can lie in padding; ``gap`` the nodata rule ``"gap"``'s
    table of mixed-cell widths, each block's slot in it and ``tau / min(tau, 1)``: its rule
    as the reference applies it, per depth with the numpy metric)."""
    k, p = grid.k, table.patch_log2
    n0 = len(idx)
    rows = np.zeros(n0, dtype=np.int64)
    cols = np.zeros(n0, dtype=np.int64)
    inside = np.zeros(n0, dtype=bool)
    use_win = win is not None
    win_a = win if use_win else np.zeros((0, 4), np.int64)
    use_cull = cull is not None
    if use_cull and not cull.empty:
        c = cull
        pf = (*(np.ascontiguousarray(v) for v in (c.o, c.px, c.py, c.ex, c.ey, c.ee_safe)),
              np.ascontiguousarray(c.ok), c.all_ok, c.ccw)  # fmt: skip
    else:
        z = np.zeros(0)
        pf = (np.zeros(2), z, z, z, z, z, _NONE_B, True, False)
    empty = bool(use_cull and cull.empty)
    o, px, py, ex, ey, ee_safe, ok, all_ok, ccw = pf
    # Qiu's Eq. 7 and the metrics naming a compiled twin (``fn.select_kernel``, e.g. Kim's)
    kernel = "qiu_rho" if fn is qiu_eq7 else getattr(fn, "select_kernel", None)
    rho_nb = getattr(nb, kernel) if kernel is not None and box_slots is None else None
    eye = np.array(camera.eye, dtype=np.float64)  # writable copies: one compiled signature
    fwd = np.array(camera.forward, dtype=np.float64)
    focal, near = float(camera.focal_px), float(camera.near)
    right, up = np.array(camera.right, dtype=np.float64), np.array(camera.up, dtype=np.float64)
    w2, h2 = camera.viewport[0] / 2.0, camera.viewport[1] / 2.0
    zr_c = np.ascontiguousarray(zr, dtype=np.float64)
    parts: list[tuple] = []
    clamped = 0
    depth = 0
    while idx.size:
        size = node_span(k, depth)
        half = half_diagonal(grid, depth)
        s = float(size)
        arr = table.depth_array(depth)
        has_arr = arr is not None
        idx, rows, cols, inside, cx, cy, delta = nb.visit(
            idx, rows, cols, inside, bx0, by1, s * grid.dx, s * grid.dy, size, use_win, win_a,
            use_cull, empty, o, px, py, ex, ey, ee_safe, ok, bool(all_ok), bool(ccw), half,
            arr if has_arr else np.zeros((1, 1, 1), np.float32), has_arr, slots,
        )  # fmt: skip
        if not idx.size:
            break
        if rho_nb is not None and kernel == "qiu_rho":
            rho = rho_nb(delta, cx, cy, idx, zr_c, half, eye, fwd, focal, near)
        elif rho_nb is not None:
            rho = rho_nb(delta, cx, cy, idx, zr_c, half, eye, right, up, fwd, focal, w2, h2)
        else:
            bx = None if box_slots is None else (boxes, (box_slots[0][idx], box_slots[1][idx]))
            rho = node_rho(fn, grid, delta, cx, cy, depth, zr[idx], camera, bx, rows, cols)
        if gap is not None:  # rho > tau also when the gap projects past min(tau, 1) px
            gaps, gap_of, gap_scale = gap
            w = gaps.delta(gap_of[idx], depth, rows, cols)
            if (w > 0).any():
                bx = None if box_slots is None else (boxes, (box_slots[0][idx], box_slots[1][idx]))
                g = node_rho(horizontal_px, grid, w, cx, cy, depth, zr[idx], camera, bx, rows, cols)
                rho = np.maximum(rho, g * gap_scale)
        if depth + p >= k:
            level = np.minimum(k, res[idx])
            parts.append((idx, depth, rows, cols, level, delta, rho))
            break
        leaf, child, n_want = nb.split(
            idx, rows, cols, inside, delta, rho, res, depth, depth + p, float(tau), min_depth
        )
        n_split = len(child[0]) // 4
        clamped += n_want - n_split
        if len(leaf[0]):
            parts.append((leaf[0], depth, *leaf[1:]))
        idx, rows, cols, inside = child
        depth += 1
    return parts, clamped
