"""Loading ``seamless-patches``' compiled selection off the render thread: one selection of a
small synthetic scene through the compiled path, which passes its whole-selection kernel the
argument types a real selection passes, so numba loads (or compiles) it here. That kernel takes
one error array per depth ``0..k − c``, so its signature depends on the store's block size
``2**k`` and the tiles' ``2**c`` cells: the scene is made for them. Without it the render
thread's first compiled selection after the viewer's warm-up spent ~28 ms loading it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from render.strategies.seamless.selection import select_layout
from streamer.camera import Camera
from streamer.levels import PatchErrorTable
from tiler.grid import BlockGrid

Block = tuple[int, int]


class _Services:
    """The frame services a seamless-patches selection reads, for 2×2 blocks of
    ``2**k + 1`` samples (one at a coarser level) with random stored errors."""

    def __init__(self, k: int) -> None:
        self.k = k
        n = 2 * (1 << k) + 1
        self.grid = BlockGrid(height=n, width=n, k=k, x0=0.0, y0=float(n - 1), dx=1.0, dy=1.0)
        self.terrain_zrange = (0.0, 20.0)
        win = np.zeros((2, 2, 4), np.int32)  # (row0, col0, rows, cols), as a store's index
        for r in range(2):
            for c in range(2):
                win[r, c] = (r << k, c << k, (1 << k) + 1, (1 << k) + 1)
        self.store = SimpleNamespace(index=SimpleNamespace(window=win))
        self.levels = {(0, 0): k, (0, 1): k - 1, (1, 0): k, (1, 1): k}
        self._rng = np.random.default_rng(0)

    def drawable(self, resident: dict[Block, int] | None = None) -> list[tuple[Block, int]]:
        return sorted(self.levels.items())

    def fill_table(self, table: PatchErrorTable, blocks: list[Block], field: str) -> None:
        for b in blocks:  # errors shrinking with depth, stored coarser past depth 6 (a cap)
            if b not in table:
                side = [1 << min(d, 6) for d in range(self.k)]
                table.add(b, [self._rng.random((s, s)) * 8.0 / (1 << d) for d, s in
                              enumerate(side)])  # fmt: skip


def warm_up_selection(k: int, c: int) -> int:
    """Run one compiled selection of the synthetic scene for blocks of ``2**k`` cells and
    tiles of ``2**c`` (numba's kernel loads here); its patch count (> 0)."""
    r = _Services(k)
    st = SimpleNamespace(
        r=r, c=c, table=PatchErrorTable(k, 1), tables=[], spike_guard=False, rho="bound",
        kernels="numba", zr=np.tile(np.array([0.0, 20.0]), (2, 2, 1)),
    )  # fmt: skip
    n = r.grid.width - 1
    camera = Camera.look_at(
        (0.3 * n, -0.6 * n, 3.0 * n), (0.5 * n, 0.5 * n, 0.0), viewport=(64, 48), near=0.5
    )
    return len(select_layout(st, camera, 0.5, None).depth)
