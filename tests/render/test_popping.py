"""Popping that sees pops: motions that cross LOD changes report them, a still camera reads 0,
and a deliberately perturbed surface is seen as a jump (the positive control)."""

from __future__ import annotations

import pytest
from gltools import make_context, rough, tile_dem

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
