"""The numpy bound kernel's two node paths (4-D broadcast, one pass per in-node offset) give
the same float32 maxima, so choosing between them by cost (``broadcast_nodes``) changes no
stored byte. Few small nodes now broadcast: a 17-sample block's depth 0 took 256 offset passes
(~5.7 ms) against one broadcast (~0.1 ms)."""

from __future__ import annotations

import numpy as np
import pytest

from tiler import static_error
from tiler.static_error import bound_errors_numpy, broadcast_nodes


def _paths(monkeypatch, grid, valid, k, *, broadcast: bool) -> list[np.ndarray]:
    """``bound_errors_numpy`` with every small-node depth on one path."""
    monkeypatch.setattr(static_error, "_BROADCAST_NODES_PER_S2", 10**9 if broadcast else 0)
    return bound_errors_numpy(grid, valid, k)


@pytest.mark.parametrize("side", [5, 9, 17, 33, 65, 129])
@pytest.mark.parametrize("holes", [False, True])
def test_both_node_paths_give_identical_bounds(monkeypatch, side, holes):
    rng = np.random.default_rng(side + 7 * holes)
    k = int(np.log2(side - 1))
    grid = (rng.standard_normal((side, side)) * 50 + 8000).astype(np.float32)
    grid += np.linspace(0, 300, side, dtype=np.float32)[None, :]
    valid = np.ones((side, side), bool)
    if holes:
        valid &= rng.random((side, side)) > 0.2
        valid[side // 2 :, side // 3 :] = False  # a cropped corner (valid_extent)
    a = _paths(monkeypatch, grid, valid, k, broadcast=True)
    b = _paths(monkeypatch, grid, valid, k, broadcast=False)
    assert len(a) == len(b) == k
    for depth, (x, y) in enumerate(zip(a, b, strict=True)):
        assert x.dtype == y.dtype and np.array_equal(x, y), (side, depth)
    assert any(np.any(x > 0) for x in a)  # a non-trivial surface was compared


def test_the_choice_covers_both_paths():
    """The comparison above is not vacuous: the default rule sends few small nodes to the
    broadcast and many to the offset passes, and large nodes always broadcast."""
    assert broadcast_nodes(1, 1, 16) and broadcast_nodes(6, 6, 2)
    assert not broadcast_nodes(64, 64, 2) and not broadcast_nodes(64, 64, 16)
    assert broadcast_nodes(512, 512, 32)


def test_control_a_changed_path_is_seen(monkeypatch):
    """Positive control: a broadcast path that drops the second triangulation's term gives
    other bounds, and the comparison above would report it."""
    rng = np.random.default_rng(3)
    grid = rng.standard_normal((17, 17)).astype(np.float32) * 100
    valid = np.ones((17, 17), bool)
    good = _paths(monkeypatch, grid, valid, 4, broadcast=False)

    def broken(f4, a, b, c, d, u, v):
        g = f4 - a
        g -= u * (b - a)
        g -= v * (c - a)
        return np.abs(g)

    monkeypatch.setattr(static_error, "_surface_dev", broken)
    bad = _paths(monkeypatch, grid, valid, 4, broadcast=True)
    assert not all(np.array_equal(x, y) for x, y in zip(good, bad, strict=True))
