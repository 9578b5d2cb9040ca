"""The measured surface of qiu's patches beside nodata (no GL): every sample a drawn triangle
covers is measured, at that triangle's height, whichever cell it lies in. A triangle with a
nodata corner is not drawn, so a sample on the border of one (its cell's diagonal, left or top
edge, corner) was left unmeasured although the neighbouring drawn triangle draws it."""

from __future__ import annotations

import numpy as np
import pytest

from render import measure
from render.select import Patches
from tiler.grid import BlockGrid

K = 4  # one 17² block


def _patches(level: int, depth: int) -> Patches:
    """Every patch of one block at ``depth``, drawn at ``level`` (no snapped edges)."""
    n = 1 << depth
    rows, cols = np.divmod(np.arange(n * n), n)
    z = np.zeros(n * n, np.int64)
    return Patches(
        blocks=np.zeros((1, 2), np.int64),
        block=z,
        depth=z + depth,
        row=rows.astype(np.int64),
        col=cols.astype(np.int64),
        level=z + level,
        delta=np.zeros(n * n),
        rho=np.zeros(n * n),
        snap=np.zeros((n * n, 4), np.int64),
        clamped=0,
        violations=0,
    )


def _measured(patches: Patches, full: np.ndarray) -> dict[tuple[int, int], float]:
    """Sample -> drawn height as the error measurement sees it (finite ones)."""
    out: dict[tuple[int, int], float] = {}
    for _, rows, cols, h in measure.lod_surface(patches, K, lambda b: full):
        for r, c, v in zip(rows.tolist(), cols.tolist(), h.tolist(), strict=True):
            if np.isfinite(v):
                out[(r, c)] = v
    return out


def _drawn(patches: Patches, full: np.ndarray) -> dict[tuple[int, int], float]:
    """Sample -> height of the drawn mesh's CPU twin, rasterised (triangles with a nodata corner
    are not drawn)."""
    grid = BlockGrid(height=17, width=17, k=K, x0=0.0, y0=0.0, dx=1.0, dy=1.0)
    tri, th = measure.patch_triangles(patches, grid, lambda b: full)
    keep = np.isfinite(th).all(axis=1)
    rows, cols, h = measure.rasterise(tri[keep], th[keep])
    return dict(zip(zip(rows.tolist(), cols.tolist(), strict=True), h.tolist(), strict=True))


@pytest.mark.parametrize(("level", "depth"), [(4, 2), (3, 1), (2, 1), (4, 0)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_drawn_sample_is_measured_at_its_drawn_height(level, depth, seed):
    rng = np.random.default_rng(seed)
    full = rng.normal(100.0, 10.0, (17, 17))
    step = 1 << (K - level)
    lattice = np.arange(0, 17, step)
    for _ in range(3):  # nodata at vertices of the drawn level: whole triangles undrawn
        full[rng.choice(lattice), rng.choice(lattice)] = np.nan
    p = _patches(level, depth)
    got, want = _measured(p, full), _drawn(p, full)
    assert set(got) == set(want)
    assert max(abs(got[s] - want[s]) for s in want) < 1e-9


def test_the_samples_beside_nodata_are_the_ones_that_were_missed():
    """The scene above where it matters: a nodata vertex at the centre of a 2-cell patch; the
    samples on the borders of its undrawn triangles that a drawn neighbour draws are measured
    (the measurement before this missed them: the count is the control)."""
    full = np.full((17, 17), 50.0)
    full[8, 8] = np.nan
    p = _patches(3, 1)  # 2 cells of 4 samples a side per patch
    got, want = _measured(p, full), _drawn(p, full)
    assert set(got) == set(want)
    # e.g. the diagonal of the cell whose lower triangle is drawn and upper is not
    undrawn = {(r, c) for r in range(17) for c in range(17)} - set(want)
    assert (8, 8) in undrawn and (6, 6) in want and (4, 6) in want


def _snapped(level: int, depth: int, snaps) -> Patches:
    """:func:`_patches` with every patch's edges snapped by ``snaps`` (N, E, S, W)."""
    p = _patches(level, depth)
    return Patches(**{**p.__dict__, "snap": np.tile(np.asarray(snaps, np.int64), (len(p), 1))})


@pytest.mark.parametrize(
    ("level", "depth", "snaps"),
    # neighbouring patches agree on their shared edges (N = S, E = W) where there are several
    [(4, 1, (1, 1, 1, 1)), (4, 1, (0, 2, 0, 2)), (4, 0, (2, 1, 3, 0)), (3, 1, (2, 1, 2, 1))],
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_drawn_sample_of_snapped_patches_is_measured(level, depth, snaps, seed):
    rng = np.random.default_rng(seed)
    full = rng.normal(100.0, 10.0, (17, 17))
    full[:, -1] = full[-1, :] = np.nan  # nodata beyond the last column and row (east, south)
    step = 1 << (K - level)
    lattice = np.arange(0, 17, step)
    for _ in range(2):
        full[rng.choice(lattice), rng.choice(lattice)] = np.nan
    p = _snapped(level, depth, snaps)
    got, want = _measured(p, full), _drawn(p, full)
    assert set(got) == set(want)
    assert max(abs(got[s] - want[s]) for s in want) < 1e-9


def test_samples_beside_a_snapped_edge_facing_nodata_are_measured():
    """A patch whose snapped east and south edges are all nodata (a neighbour wholly nodata
    beyond them): the drawn samples on the last valid column and row, which the regular cells
    draw, were handed to the edge strips, whose triangles all have a nodata corner, and left
    unmeasured. The west and north edges (valid, snapped) are the control."""
    full = np.full((17, 17), 50.0) + np.add.outer(np.arange(17.0), np.arange(17.0))
    full[:, 16] = full[16, :] = np.nan
    p = _snapped(4, 0, (1, 1, 1, 1))  # one patch of 16 cells a side, every edge snapped
    got, want = _measured(p, full), _drawn(p, full)
    # (0, 15) and (15, 0) lie on the snapped N and W edges, in a strip triangle with a corner
    # in the nodata column and row: not drawn
    last = {(r, 15) for r in range(1, 16)} | {(15, c) for c in range(1, 16)}
    assert last <= set(want) and last <= set(got)
    assert set(got) == set(want)
