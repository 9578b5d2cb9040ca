"""Pure known answers of issue 12's pieces (no GL): mask-boundary nodes, raised errors, the
colour ramp's mapping and the near plane."""

from __future__ import annotations

import math

import numpy as np
import pytest

from render.frame_types import ramp_map
from render.views import MIN_NEAR, near_plane
from streamer.nodata import NODATA_RULES, check_rule, gap_widths, mixed_nodes, raise_mixed


def test_mixed_nodes_known_answer():
    valid = np.ones((5, 5), bool)
    assert not any(m.any() for m in mixed_nodes(valid, 2))  # quiet case
    valid[0, 0] = False
    m = mixed_nodes(valid, 2)
    assert [a.shape for a in m] == [(1, 1), (2, 2), (4, 4)]
    assert m[2].sum() == 1 and m[2][0, 0] and m[1].sum() == 1 and m[1][0, 0] and m[0][0, 0]
    valid[:] = False
    assert not any(a.any() for a in mixed_nodes(valid, 2))  # all nodata: nothing to refine
    valid[2, :] = True  # a valid row through the middle: both middle-row nodes at depth 1
    assert mixed_nodes(valid, 2)[1].all()


def test_gap_widths_are_the_mixed_cells_diagonals():
    valid = np.ones((5, 5), bool)
    valid[0, 0] = False
    w = gap_widths(valid, 2, 3.0, 4.0)
    assert [a.shape for a in w] == [(1, 1), (2, 2)]  # depths 0..k-1: level k leaves no gap
    assert w[0][0, 0] == pytest.approx(4 * 5.0) and w[1][0, 0] == pytest.approx(2 * 5.0)
    assert (w[1][[0, 1, 1], [1, 0, 1]] == 0).all()  # cells wholly valid
    assert not any(a.any() for a in gap_widths(np.ones((5, 5), bool), 2, 1.0, 1.0))


def test_nodata_rules_are_named_and_checked():
    assert NODATA_RULES == ("full", "gap") and check_rule("gap") == "gap"
    with pytest.raises(ValueError, match="unknown nodata rule 'fast'.*full"):
        check_rule("fast")


def test_raise_mixed_raises_tiles_below_the_cap():
    valid = np.ones((9, 9), bool)
    valid[8, 8] = False  # the south-east corner sample
    mixed = mixed_nodes(valid, 3)
    field = [np.zeros((1, 1), np.float32), np.ones((2, 2), np.float32),
             np.full((2, 2), 2.0, np.float32)]  # depth 2 capped to 2x2 tiles  # fmt: skip
    out = raise_mixed(field, mixed)
    assert np.isinf(out[0]).all()
    assert np.isinf(out[1][1, 1]) and (out[1][[0, 0, 1], [0, 1, 0]] == 1).all()
    assert np.isinf(out[2][1, 1]) and np.isfinite(out[2]).sum() == 3
    assert field[1][1, 1] == 1  # the stored field itself is untouched


@pytest.mark.parametrize(
    ("zr", "zref", "expected"),
    [((5.0, 5.0), 5.0, (0.0, 0.0, 0.0, -5.0)),  # constant: one colour
     ((-4000.0, -1000.0), -2500.0, (-1500.0, 1 / 3000, 0.0, 2500.0)),  # all negative: land ramp
     ((-100.0, 400.0), 150.0, (-150.0, 1 / 400, 1 / 100, -150.0))],  # crosses 0: sea below 0
)  # fmt: skip
def test_ramp_map_known_answers(zr, zref, expected):
    assert ramp_map(zr, zref) == pytest.approx(expected)


class _Store:
    class grid:  # noqa: N801 - mimics TerrainStore.grid (no block geometry: global top)
        extent = (0.0, 0.0, 1000.0, 1000.0)

    class index:  # noqa: N801
        zmin = np.array([[0.0]])
        zmax = np.array([[100.0]])


def test_near_plane_follows_the_clearance():
    t = math.tan(math.radians(22.5)) * math.hypot(1, 4 / 3)
    assert near_plane(_Store(), (0, 0, 100.5), t, 5.0) == pytest.approx(0.25 / (1 + t))
    assert near_plane(_Store(), (0, 0, 5000.0), t, 5.0) == 5.0  # capped by the scene rule
    assert near_plane(_Store(), (0, 0, 50.0), t, 5.0) == MIN_NEAR  # inside the terrain


@pytest.mark.parametrize("p", [0, 8, -1])
def test_patch_sizes_that_cannot_be_stitched_are_refused(p):
    """One-cell patches (``patch_log2 = 0``) cannot snap an edge to a coarser neighbour, so
    stitching would split the whole view to one level (it did not settle in 64 rounds on
    N44W072): refused with the value and what to use."""
    from render.errors import RenderError
    from render.frame_types import RenderConfig

    with pytest.raises(RenderError, match=f"patch_log2 must be in 1..7, got {p}"):
        RenderConfig(patch_log2=p)
    assert RenderConfig(patch_log2=1).patch_log2 == 1 and RenderConfig(patch_log2=7).patch_log2 == 7
