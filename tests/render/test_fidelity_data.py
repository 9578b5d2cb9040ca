"""Fidelity at the extremes (issue 12), the data side: heights far from zero without jitter
(heights relative to the store's reference height, subtracted in float64 before float32)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import fractal
from gltools import make_context, tile_dem

from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy, strategy_names
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
NAMES = strategy_names()
OPTIONS = {"chunk-tessellation": {"chunk_log2": 3}, "seamless-patches": {"res_log2": 3}}
EVEREST = 8848.0
#: pixel budgets: share of pixels whose largest channel differs by more than 2 levels
PLATEAU_BUDGET, MOVE_BUDGET = 0.01, 0.01


def _relief() -> np.ndarray:
    """5 cm of relief on a 65² float64 DEM (1 m cells)."""
    d = fractal((65, 65), seed=4).astype(np.float64)
    return 0.05 * (d - d.min()) / np.ptp(d)


@pytest.fixture(scope="module")
def plateaus(tmp_path_factory):
    rel = _relief()
    return {
        z0: tile_dem(tmp_path_factory.mktemp(f"p{int(z0)}"), rel + z0, 65, cell=1.0)
        for z0 in (0.0, EVEREST)
    }


def _image(path, name, z0, dx=0.0):
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy(name, r, **OPTIONS.get(name, {}))
    g = r.grid
    cam = Camera.look_at(
        (g.x0 + 32 + dx, g.y0 - 75.0, z0 + 12.0), (g.x0 + 32 + dx, g.y0 - 32, z0), viewport=SIZE,
        near=0.05, far=1e4,
    )  # fmt: skip
    sel, _ = st.select(cam, 0.0)
    st.draw(cam, sel)
    img = r.image().astype(int)
    r.close()
    return img


def _changed(a, b) -> float:
    return float((np.abs(a - b).max(-1) > 2).mean())


@pytest.mark.parametrize("name", NAMES)
def test_a_plateau_at_8848_m_renders_like_the_same_relief_at_0_m(plateaus, name):
    low = _image(plateaus[0.0], name, 0.0)
    high = _image(plateaus[EVEREST], name, EVEREST)
    diff = _changed(low, high)
    assert diff <= PLATEAU_BUDGET, f"{diff:.1%} of the pixels differ"


@pytest.mark.parametrize("name", NAMES)
def test_a_millimetre_camera_move_at_8848_m_changes_few_pixels(plateaus, name):
    a = _image(plateaus[EVEREST], name, EVEREST)
    b = _image(plateaus[EVEREST], name, EVEREST, dx=0.001)
    diff = _changed(a, b)
    assert diff <= MOVE_BUDGET, f"{diff:.1%} of the pixels changed"
