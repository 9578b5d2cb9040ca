"""The snapping excess (:func:`render.snap_error.snap_excess`) against the drawn surface: on a
snapped patch every sample's error is at most the unsnapped error plus the excess, and the
excess is never below the measured ``|I - S|``; positive control: snapping alone exceeds the
unsnapped error (what the excess is for). Pure numpy (the CPU twin of the patch mesh)."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal

from render import measure
from render.select import Patches
from render.snap_error import snap_exact, snap_excess
from tiler.static_error import bound_errors

K = 5  # one block of 33² samples


def _patch(level: int, snaps) -> Patches:
    z = np.zeros(1, np.int64)
    return Patches(
        blocks=np.zeros((1, 2), np.int64), block=z, depth=z, row=z, col=z,
        level=np.array([level]), delta=np.zeros(1), rho=np.zeros(1),
        snap=np.array([snaps], np.int64), clamped=0, violations=0,
    )  # fmt: skip


def drawn(h: np.ndarray, level: int, snaps) -> np.ndarray:
    """The patch's drawn heights at every full-resolution sample (NaN where not covered)."""
    out = np.full(h.shape, np.nan)
    for _, rows, cols, hl in measure.lod_surface(_patch(level, snaps), K, lambda b: h):
        out[rows, cols] = np.fmax(out[rows, cols], hl)
    return out


CASES = [(3, (1, 2, 0, 3)), (3, (3, 0, 1, 0)), (2, (1, 1, 2, 2)), (4, (2, 0, 0, 1))]


@pytest.mark.parametrize(("level", "snaps"), CASES)
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_snapped_error_within_delta_plus_excess(level, snaps, seed):
    h = fractal((33, 33), seed=seed).astype(np.float64) * 30.0
    step = 1 << (K - level)
    verts = h[::step, ::step]
    ex = snap_excess(np.array([level]), np.array([snaps]), lambda idx: verts[None])[0]
    assert ((ex > 0) <= (np.array(snaps) > 0)).all()  # only snapped edges have an excess
    flat = drawn(h, level, (0, 0, 0, 0))
    snapped = drawn(h, level, snaps)
    delta = np.nanmax(np.abs(h - flat))
    err = np.abs(h - snapped)
    assert np.nanmax(err) <= delta + ex.max() + 1e-9
    assert np.nanmax(np.abs(snapped - flat)) <= ex.max() + 1e-9
    # with the cells' own stored errors: a bound on the strips' whole error
    cells = bound_errors(h, np.ones(h.shape, bool), K)[level] if level < K else None
    n = 1 << level
    cb = np.zeros((1, n, n)) if cells is None else cells[None]
    total = snap_excess(np.array([level]), np.array([snaps]), lambda idx: verts[None],
                        lambda idx: cb)[0]  # fmt: skip
    assert np.nanmax(err) <= max(delta, total.max()) + 1e-9
    assert total.max() <= cb.max() + ex.max() + 1e-9  # never above the patch-wide sum
    # at full resolution: the exact strip error, attained by samples and covering them
    exact = snap_exact(np.array([level]), np.array([K - level]), np.array([snaps]),
                       lambda idx: h[None])[0]  # fmt: skip
    assert np.nanmax(err) <= max(delta, exact.max()) + 1e-9
    assert exact.max() <= np.nanmax(err) + 1e-9
    assert exact.max() <= total.max() + 1e-9


def test_positive_control_snapping_exceeds_the_unsnapped_error():
    """Snapping alone breaks the unsnapped error, 0.6 of the excess misses ``|I - S|`` and
    0.9 of the exact strip error misses the snapped surface's error."""
    over = short = low = 0
    for seed in range(1, 6):
        h = fractal((33, 33), seed=seed).astype(np.float64) * 30.0
        for level, snaps in CASES:
            flat, snapped = drawn(h, level, (0, 0, 0, 0)), drawn(h, level, snaps)
            over += int(np.nanmax(np.abs(h - snapped)) > np.nanmax(np.abs(h - flat)) + 1e-9)
            verts = h[:: 1 << (K - level), :: 1 << (K - level)]
            ex = snap_excess(np.array([level]), np.array([snaps]), lambda idx, v=verts: v[None])
            short += int(np.nanmax(np.abs(snapped - flat)) > 0.6 * ex.max())
            exact = snap_exact(np.array([level]), np.array([K - level]), np.array([snaps]),
                               lambda idx, g=h: g[None])  # fmt: skip
            low += int(np.nanmax(np.abs(h - snapped)) > max(np.nanmax(np.abs(h - flat)),
                                                            0.9 * exact.max()))  # fmt: skip
    assert over > 0 and short > 0 and low > 0, (over, short, low)


def test_excess_is_zero_without_snaps_and_for_a_plane():
    i, j = np.meshgrid(np.arange(9.0), np.arange(9.0))
    plane = 3.0 * i - 2.0 * j + 7.0  # I = S on a plane: no excess whatever the snaps
    ex = snap_excess(np.array([3, 3]), np.array([[0, 0, 0, 0], [2, 1, 3, 1]]),
                     lambda idx: np.stack([plane] * len(idx)))  # fmt: skip
    assert np.allclose(ex, 0.0, atol=1e-9)


def test_masked_vertices_use_the_range_bound():
    h = fractal((9, 9), seed=4).astype(np.float64) * 30.0
    hm = h.copy()
    hm[4, 4] = np.nan
    a = snap_excess(np.array([3]), np.array([[2, 0, 0, 0]]), lambda idx: h[None])[0]
    b = snap_excess(np.array([3]), np.array([[2, 0, 0, 0]]), lambda idx: hm[None])[0]
    assert np.isfinite(b).all() and b[0] >= a[0] - 1e-9
