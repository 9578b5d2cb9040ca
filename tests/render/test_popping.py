"""Popping that sees pops: motions that cross LOD changes report them, a still camera reads 0,
and a deliberately perturbed surface is seen as a jump (the positive control)."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.compare import dolly, popping
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (128, 96)


@pytest.fixture(scope="module")
def strat(tmp_path_factory):
    ctx = make_context()
    s = open_store(tile_dem(tmp_path_factory.mktemp("pop"), rough(129, 3), 33))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=ctx)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield get_strategy("qiu", r)
    r.close()


CAM = Camera((500015.0 + 1920, 4998000.0 - 1500, 1500.0), pitch=-40.0, viewport=SIZE, far=1e5)


class Perturbed:
    """``strat`` whose drawn surface rises by ``dz`` metres every frame (a fake pop)."""

    def __init__(self, strat, dz: float) -> None:
        self.s, self.r, self.dz, self.n = strat, strat.r, dz, 0

    def select(self, *a, **kw):
        return self.s.select(*a, **kw)

    def surface(self, cam, sel):
        rows, cols, h = self.s.surface(cam, sel)
        self.n += 1
        return rows, cols, h + self.dz * self.n


def test_a_still_camera_does_not_pop(strat):
    pop = popping(strat, [CAM] * 4, 2.0, "qiu")
    assert (pop.max_px, pop.lod_frames, pop.frames) == (0.0, 0, 3)


def test_a_perturbed_surface_pops(strat):
    pop = popping(Perturbed(strat, 50.0), [CAM] * 4, 2.0, "qiu")
    assert pop.max_px > 1.0 and pop.lod_frames == 3


def test_a_dolly_crosses_lod_changes(strat):
    pop = popping(strat, dolly(CAM, 1500.0, 8), 2.0, "qiu")
    assert pop.frames == 8 and pop.lod_frames >= 2 and pop.max_px > 0.0


class Culled:
    """``strat`` whose drawn surface loses one more sample every frame, heights unchanged
    (what a camera panning over a fixed LOD does at the view's edge)."""

    def __init__(self, strat) -> None:
        self.s, self.r, self.n = strat, strat.r, 0

    def select(self, *a, **kw):
        return self.s.select(*a, **kw)

    def surface(self, cam, sel):
        rows, cols, h = self.s.surface(cam, sel)
        self.n += 1
        return rows[self.n :], cols[self.n :], h[self.n :]


def test_culling_alone_is_not_a_lod_change(strat):
    """Samples leaving the view with no height changed were counted as LOD frames; the
    control (``Perturbed`` above, heights changed) is counted."""
    pop = popping(Culled(strat), [CAM] * 4, 2.0, "qiu")
    assert (pop.max_px, pop.lod_frames, pop.frames) == (0.0, 0, 3)
    assert popping(Perturbed(strat, 0.5), [CAM] * 4, 2.0, "qiu").lod_frames == 3


class PerturbedWhere:
    """``strat`` whose drawn surface rises by ``dz`` metres every frame at the samples
    ``on_screen`` selects (in ``CAM``'s view or not) and nowhere else."""

    def __init__(self, strat, dz: float, on_screen: bool) -> None:
        self.s, self.r, self.dz, self.on, self.n = strat, strat.r, dz, on_screen, 0

    def select(self, *a, **kw):
        return self.s.select(*a, **kw)

    def surface(self, cam, sel):
        rows, cols, h = self.s.surface(cam, sel)
        x, y = self.r.grid.sample_xy(rows, cols)
        seen = np.zeros((2, *rows.shape), bool)  # in view at no height / at every height
        seen[1] = True
        for m in range(5):  # the heights the 4 frames give
            at = np.zeros(rows.shape, bool)
            at[measure.project_in_view(cam, x, y, h + self.dz * m)[3]] = True
            seen[0] |= at
            seen[1] &= at
        pick = seen[1] if self.on else ~seen[0] & np.isfinite(h)
        assert pick.any()  # the view's patches reach beyond its edges
        self.n += 1
        return rows, cols, np.where(pick, h + self.dz * self.n, h)


def test_a_change_off_screen_is_not_a_lod_change(strat):
    """Heights changed only at samples outside the later camera's view were counted as LOD
    frames (with 0.00 px); the same change at samples in view is counted (the control)."""
    off = popping(PerturbedWhere(strat, 50.0, on_screen=False), [CAM] * 4, 2.0, "qiu")
    assert (off.max_px, off.lod_frames, off.frames) == (0.0, 0, 3)
    on = popping(PerturbedWhere(strat, 50.0, on_screen=True), [CAM] * 4, 2.0, "qiu")
    assert on.max_px > 1.0 and on.lod_frames == 3


def test_a_single_camera_measures_no_popping(strat):
    """With no pair of frames nothing is measured: None, not a perfect 0.0 px."""
    pop = popping(strat, [CAM], 2.0, "qiu")
    assert (pop.max_px, pop.lod_frames, pop.frames) == (None, 0, 0)
    assert popping(strat, [CAM] * 2, 2.0, "qiu").max_px == 0.0  # one pair: measured
