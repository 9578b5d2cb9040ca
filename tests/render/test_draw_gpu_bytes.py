"""A drawn frame's GPU bytes (``render --json``'s ``gpu_bytes``) count the strategy's own
buffers, as ``tradeoff`` and ``compare`` do."""

from __future__ import annotations

import pytest
from gltools import make_context, rough, tile_dem

from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy, strategy_names
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (128, 96)
OPTIONS = {
    "chunk-tessellation": {"chunk_log2": 3},
    "chunk-tessellation-gpu": {"chunk_log2": 3},
    "seamless-patches": {"res_log2": 3},
}
CAM = Camera((500015.0 + 960, 5000000.0 - 15 - 1800, 900.0), pitch=-45.0, viewport=SIZE, far=1e5)


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    s = open_store(tile_dem(tmp_path_factory.mktemp("gpub"), rough(65, 5), 33))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=make_context())
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield r
    r.close()


@pytest.mark.parametrize("name", strategy_names())
def test_drawn_gpu_bytes_count_the_strategys_own_buffers(renderer, name):
    """seamless-patches' cached meshes and chunk-tessellation-gpu's error buffer were left out
    of the frame's ``gpu_bytes`` (only geometry-splitting counted its textures)."""
    strat = get_strategy(name, renderer, **OPTIONS.get(name, {}))
    sel, _ = strat.select(CAM, 2.0, "qiu")
    st = strat.draw(CAM, sel)
    own = strat.own_gpu_bytes()
    if name in ("seamless-patches", "chunk-tessellation-gpu", "geometry-splitting"):
        assert own > 0  # the case the check is about: buffers of its own
    assert st.gpu_bytes == renderer.height_bytes + own
