"""Loading the compiled CLOD walk's kernels off the render thread: selections of a small
synthetic scene through :func:`render.select.select_patches` with the compiled walk, one per
metric with a compiled twin (Qiu's Eq. 7, the default strategy's, and Kim's, which
``chunk-tessellation`` uses), so numba loads (or compiles) ``visit``, ``split`` and the metric's
kernel with a real frame's argument types here. Without it the render thread's first compiled
``qiu`` selection after the viewer's warm-up spent ~12 ms loading them
(``bench/kernel_switch.py``)."""

from __future__ import annotations

import numpy as np

from render.select import select_patches
from render.strategies.chunk_tess.pure import kim_metric
from streamer.camera import Camera
from streamer.frustum import frustum_hull
from streamer.levels import PatchErrorTable
from tiler.grid import BlockGrid


def warm_up_walk(k: int = 4, patch_log2: int = 1) -> int:
    """Select a 2×2-block scene of ``2**k + 1``-sample blocks once per compiled metric; the
    patches selected in all (> 0)."""
    n = 2 * (1 << k) + 1
    grid = BlockGrid(height=n, width=n, k=k, x0=0.0, y0=float(n - 1), dx=1.0, dy=1.0)
    rng = np.random.default_rng(0)
    table = PatchErrorTable(k, patch_log2)
    blocks = [(0, 0), (0, 1), (1, 0), (1, 1)]
    for b in blocks:  # errors shrinking with depth, as stored ones do
        table.add(b, [rng.random((1 << d,) * 2) * 8.0 / (1 << d) for d in range(k)])
    zranges = np.array([[0.0, 20.0]] * len(blocks))
    camera = Camera.look_at(
        (0.3 * n, -0.6 * n, 3.0 * n), (0.5 * n, 0.5 * n, 0.0), viewport=(64, 48), near=0.5
    )
    poly = frustum_hull(camera, (0.0, 20.0))
    total = 0
    for metric in ("qiu", kim_metric):
        patches = select_patches(
            grid, blocks, table, camera, 0.5, metric, poly,
            resident=[k, k - 1, k, k], zranges=zranges, kernels="numba",
        )  # fmt: skip
        total += len(patches.depth)
    return total
