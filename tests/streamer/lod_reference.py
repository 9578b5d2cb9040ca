"""Reference LOD selection (test-only): every leaf node of Qiu's breadth-first selection.

Moved out of ``streamer.lod`` (issue 9): the streamer uses :class:`streamer.levels.PatchErrorTable`,
which is tested to equal :func:`select_many`'s needed levels. Node geometry comes from
:mod:`tiler.quadtree` like everywhere else.

:func:`select_nodes` walks one block's quadtree breadth-first, level by level over arrays of
nodes: cull a node whose bounding circle (diameter = node diagonal) misses the ground polygon,
split it while ``metric(delta) > tau``. A node at depth ``d`` is drawn as a patch of
``2**patch_log2`` cells, i.e. from the level ``min(k, d + patch_log2)`` grid, so its ``delta`` is
the largest stored error of its descendants at depth ``d + patch_log2`` (0 at full resolution).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from streamer.camera import Camera
from streamer.errors import LodError
from streamer.frustum import as_polygon, polygon_meets_circles
from streamer.lod import Metric, get_metric
from tiler import quadtree
from tiler.grid import BlockGrid

# --- error fields -----------------------------------------------------------------------------


def _pooled(arr: np.ndarray, depth: int) -> tuple[np.ndarray, int]:
    """``(..., n, n)`` errors max-pooled to at most ``2**depth`` per side, and the index shift."""
    n, nd = arr.shape[-1], 1 << depth
    if n >= nd:
        s = n // nd
        return arr.reshape(*arr.shape[:-2], nd, s, nd, s).max(axis=(-3, -1)), 0
    return arr, depth - (n.bit_length() - 1)


def subtree_errors(
    field: Sequence[np.ndarray], depth: int, rows: np.ndarray, cols: np.ndarray, below: int
) -> np.ndarray:
    """Vectorised :func:`tiler.static_error.subtree_error`: max error ``below`` depths down."""
    if depth < 0 or below < 0 or depth + below >= len(field):
        raise LodError(f"depth {depth} + below {below} must be < {len(field)} stored depths")
    pooled, shift = _pooled(np.asarray(field[depth + below], dtype=np.float64), depth)
    rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
    return pooled[rows >> shift, cols >> shift]


def _check_field(field: Sequence[np.ndarray], k: int, shapes: list[tuple[int, ...]]) -> None:
    """Raise ``LodError`` unless ``field`` is an unpacked field of a ``2**k+1`` block."""
    if len(field) != k:
        raise LodError(f"field must hold one array per depth 0..{k - 1}, got {len(field)}")
    for d, a in enumerate(field):
        n = np.shape(a)[0] if np.ndim(a) == 2 else -1
        if np.shape(a) != (n, n) or n < 1 or n & (n - 1) or n > (1 << d):
            raise LodError(
                f"field[{d}] must be a square power-of-two array of side <= {1 << d}, "
                f"got shape {np.shape(a)}"
            )
        if len(shapes) > d and np.shape(a) != shapes[d]:
            raise LodError(f"all fields must share one cap: field[{d}] has shape {np.shape(a)}")


# --- selection --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class NodeSelection:
    """Leaf nodes ``(depth, row, col)`` of one block, their level, delta and screen error."""

    depth: np.ndarray
    row: np.ndarray
    col: np.ndarray
    level: np.ndarray
    delta: np.ndarray
    rho: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.depth)
        for name in ("row", "col", "level", "delta", "rho"):
            if len(getattr(self, name)) != n:
                raise LodError(f"{name} has {len(getattr(self, name))} entries, depth has {n}")

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def needed_level(self) -> int:
        """Largest level any leaf needs (0 if the block is culled)."""
        return int(self.level.max()) if len(self.level) else 0


def node_centres(
    grid: BlockGrid, block: tuple[int, int], depth: int, rows: np.ndarray, cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """World ``(x, y)`` centres of nodes of one block, and their half diagonal."""
    n = np.shape(rows)
    br, bc = np.full(n, block[0]), np.full(n, block[1])
    cx, cy = quadtree.node_centres(grid, br, bc, depth, rows, cols)
    return cx, cy, quadtree.half_diagonal(grid, depth)


def _check_common(tau: float, patch_log2: int) -> float:
    """Validate ``tau`` and ``patch_log2``; return ``tau`` as a float."""
    try:
        ok = not isinstance(tau, bool) and float(tau) >= 0.0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise LodError(f"tau must be a pixel threshold >= 0, got {tau!r}")
    if isinstance(patch_log2, bool) or not isinstance(patch_log2, int) or patch_log2 < 0:
        raise LodError(f"patch_log2 must be an integer >= 0, got {patch_log2!r}")
    return float(tau)


def select_many(
    grid: BlockGrid,
    blocks: Sequence[tuple[int, int]] | np.ndarray,
    fields: Sequence[Sequence[np.ndarray]],
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    patch_log2: int = 4,
    *,
    zranges: Sequence[tuple[float, float]] | np.ndarray,
) -> list[NodeSelection]:
    """:func:`select_nodes` for many blocks at once (one pass per depth over all their nodes).

    ``fields[i]`` and ``zranges[i]`` belong to ``blocks[i]`` (a single ``(zmin, zmax)`` is
    shared); all fields must have the same ``cap``. Returns one selection per block, in order.
    """
    k = grid.k
    tau = _check_common(tau, patch_log2)
    blk = np.asarray(blocks, dtype=np.int64).reshape(-1, 2)
    nb = len(blk)
    for br, bc in blk.tolist():
        if not (0 <= br < grid.rows and 0 <= bc < grid.cols):
            raise LodError(f"block ({br}, {bc}) is outside the {grid.rows}x{grid.cols} grid")
    if len(fields) != nb:
        raise LodError(f"got {len(fields)} fields for {nb} blocks")
    zr = np.asarray(zranges, dtype=np.float64)
    if zr.shape == (2,):
        zr = np.broadcast_to(zr, (nb, 2))
    if zr.shape != (nb, 2) or not np.isfinite(zr).all() or (zr[:, 0] > zr[:, 1]).any():
        raise LodError(
            f"zranges must be finite (zmin, zmax) with zmin <= zmax, one per block, got "
            f"{np.asarray(zranges).tolist()}"
        )
    shapes: list[tuple[int, ...]] = []
    for f in fields:
        _check_field(f, k, shapes)
        shapes = shapes or [np.shape(a) for a in f]
    fn = get_metric(metric)
    poly = None if polygon is None else as_polygon(polygon)
    if nb == 0:
        return []
    zmid, zhalf = 0.5 * (zr[:, 0] + zr[:, 1]), 0.5 * (zr[:, 1] - zr[:, 0])

    names = ("block", "depth", "row", "col", "delta", "rho")
    out: dict[str, list[np.ndarray]] = {n: [] for n in names}
    b = np.arange(nb)
    rows = np.zeros(nb, dtype=np.int64)
    cols = np.zeros(nb, dtype=np.int64)
    depth = 0
    while b.size:
        cx, cy = quadtree.node_centres(grid, blk[b, 0], blk[b, 1], depth, rows, cols)
        half_diag = quadtree.half_diagonal(grid, depth)
        if poly is not None:
            keep = polygon_meets_circles(poly, cx, cy, half_diag)
            b, rows, cols, cx, cy = b[keep], rows[keep], cols[keep], cx[keep], cy[keep]
            if not b.size:
                break
        refinable = depth + patch_log2 < k
        if refinable:
            stacked = np.stack([np.asarray(f[depth + patch_log2]) for f in fields])
            pooled, shift = _pooled(stacked.astype(np.float64), depth)
            delta = pooled[b, rows >> shift, cols >> shift]
        else:
            delta = np.zeros(b.shape)
        centres = np.stack([cx, cy, zmid[b]], axis=1)
        radius = quadtree.sphere_radius(half_diag, zhalf[b])
        rho = np.asarray(fn(delta, centres, radius, camera), dtype=np.float64)
        if rho.shape != delta.shape:
            raise LodError(f"metric returned shape {rho.shape}, expected {delta.shape}")
        split = ~(rho <= tau) & refinable
        leaf = ~split
        for name, v in (("block", b), ("row", rows), ("col", cols), ("delta", delta), ("rho", rho)):
            out[name].append(v[leaf])
        out["depth"].append(np.full(int(leaf.sum()), depth, dtype=np.int64))
        b, rows, cols = quadtree.split_children(b, rows, cols, split)
        depth += 1

    empty = {"delta": np.zeros(0), "rho": np.zeros(0)}
    cat = {
        n: np.concatenate(out[n]) if out[n] else empty.get(n, np.zeros(0, np.int64)) for n in names
    }
    order = np.argsort(cat["block"], kind="stable")
    bounds = np.cumsum(np.bincount(cat["block"], minlength=nb))[:-1]
    parts = {n: np.split(cat[n][order], bounds) for n in names[1:]}
    return [
        NodeSelection(
            depth=parts["depth"][i].astype(np.int64),
            row=parts["row"][i].astype(np.int64),
            col=parts["col"][i].astype(np.int64),
            level=np.minimum(k, parts["depth"][i] + patch_log2).astype(np.int64),
            delta=parts["delta"][i].astype(np.float64),
            rho=parts["rho"][i].astype(np.float64),
        )
        for i in range(nb)
    ]


def select_nodes(
    grid: BlockGrid,
    block: tuple[int, int],
    field: Sequence[np.ndarray],
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    patch_log2: int = 4,
    *,
    zrange: tuple[float, float],
) -> NodeSelection:
    """Qiu's Sect. 3.3 selection for one block: cull by bounding circle, split while rho > tau.

    ``polygon`` (ground, e.g. :func:`streamer.frustum.view_triangle`) or None for no culling;
    ``zrange`` the block's (min, max) sample heights: node centres sit at its middle and the
    spheres given to the metric enclose the node's box over it. Leaves need level
    ``min(k, depth + patch_log2)``. Breadth-first over arrays of nodes, one depth at a time.
    """
    (sel,) = select_many(
        grid, [block], [field], camera, tau, metric, polygon, patch_log2, zranges=[zrange]
    )
    return sel


def needed_level(
    grid: BlockGrid,
    block: tuple[int, int],
    field: Sequence[np.ndarray],
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    patch_log2: int = 4,
    *,
    zrange: tuple[float, float],
) -> int:
    """Largest level over the block's selected leaves (0 if the block is culled)."""
    sel = select_nodes(grid, block, field, camera, tau, metric, polygon, patch_log2, zrange=zrange)
    return sel.needed_level


def needed_levels(
    grid: BlockGrid,
    blocks: Sequence[tuple[int, int]] | np.ndarray,
    fields: Sequence[Sequence[np.ndarray]],
    camera: Camera,
    tau: float,
    metric: str | Metric,
    polygon: np.ndarray | None,
    patch_log2: int = 4,
    *,
    zranges: Sequence[tuple[float, float]] | np.ndarray,
) -> np.ndarray:
    """:func:`needed_level` of many blocks at once, as an int64 array aligned with ``blocks``."""
    sels = select_many(
        grid, blocks, fields, camera, tau, metric, polygon, patch_log2, zranges=zranges
    )
    return np.array([s.needed_level for s in sels], dtype=np.int64)
