"""A renderer's GL work happens in its own context, whatever other code made current: its GL
objects live there and their names mean other objects (or none) in any other context. A
renderer made while another context was current (``tradeoff`` without a renderer left its own
current) drew with the names of its framebuffer, height pages and meshes looked up in the
shared context: GL errors, or a segfault in the draw where those names were other, smaller
buffers (tests/render/test_cracks.py after test_gl_joinable.py). Fresh contexts here hold no
objects, so the unfixed code fails with GL errors instead of crashing. Also: the instances of a
patch the GPU does not hold are a clear error, not an out-of-slot fetch."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gltools import rough, tile_dem
from shared_gl import gl_context, make_current

import render.pipeline as pipeline
from render.errors import RenderError
from render.gpu import create_context
from render.measure import is_clear
from render.renderer import CLEAR, RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
SIZE = (96, 64)


@pytest.fixture(scope="module")
def path(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("context"), rough(129, 5, amp=20.0), 65)


def _camera(r: TerrainRenderer) -> Camera:
    x0, y0, x1, _ = r.grid.extent
    return Camera(((x0 + x1) / 2, y0 + 800, 1500.0), pitch=-30.0, viewport=SIZE, near=5.0, far=1e5)


def _renderer(path, ctx=None, levels=None, skip=()) -> TerrainRenderer:
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=ctx)
    for b in s.blocks():
        if b not in skip:
            r.upload(b, s.read_levels(b, s.k if levels is None else levels))
    return r


def _draw(r: TerrainRenderer, between=None) -> np.ndarray:
    cam = _camera(r)
    sel, _ = r.select(cam, 2.0)
    if between is not None:
        make_current(between)  # other code's context, current when the renderer draws
    r.draw(cam, sel, clear=CLEAR)
    return r.image()


@pytest.fixture(scope="module")
def reference(path):
    make_current(gl_context())
    r = _renderer(path, gl_context())
    img = _draw(r)
    r.close()
    assert (~is_clear(img, CLEAR)).mean() > 0.3, "the view must show terrain"
    return img


@pytest.mark.parametrize("made_under", ["foreign", "own"])
def test_a_renderer_draws_in_its_own_context_whatever_is_current(path, reference, made_under):
    own = create_context()  # fresh: holds no object a stray name could mean
    foreign = create_context()  # current now, like the one a renderer-less tradeoff left
    try:
        if made_under == "own":
            make_current(own)
        r = _renderer(path, own)  # made while ``foreign`` (or ``own``) is current
        # drawn with the other one current: the shared context after a test's fixture made it
        # current (test_cracks), or a foreign one made current by other code in between
        img = _draw(r, between=own if made_under == "foreign" else foreign)
        np.testing.assert_array_equal(img, reference)
        sel, _ = r.select(_camera(r), 2.0)
        qiu = get_strategy("qiu", r)
        make_current(own)
        tri, h = qiu.gpu_triangles(_camera(r), sel)  # transform feedback read-back
        make_current(foreign)
        tri_f, h_f = qiu.gpu_triangles(_camera(r), sel)
        assert len(tri) > 0
        np.testing.assert_array_equal(tri_f, tri)
        np.testing.assert_array_equal(h_f, h)
        r.close()
        make_current(own)
        assert own.error == "GL_NO_ERROR"
    finally:
        make_current(gl_context())
        own.release()
        foreign.release()


def test_a_renderer_made_by_render_view_is_closed_there(path, monkeypatch):
    closed = []
    close = TerrainRenderer.close
    monkeypatch.setattr(TerrainRenderer, "close", lambda self: (closed.append(self), close(self)))
    s = open_store(path)
    r = _renderer(path, gl_context())
    cam = _camera(r)
    pipeline.render_view(s, cam, tau=2.0, patch_log2=2, renderer=r)
    assert closed == []  # the caller's renderer stays open
    img, _ = pipeline.render_view(s, cam, tau=2.0, patch_log2=2)  # makes its own context
    assert len(closed) == 1 and closed[0] is not r and (~is_clear(img, CLEAR)).any()
    _draw(r)  # the caller's renderer draws on after the other context went
    r.close()


def test_patches_the_gpu_does_not_hold_are_an_error_before_the_draw(path):
    full = _renderer(path, gl_context())
    cam = _camera(full)
    sel, _ = full.select(cam, 0.0, full=True)  # every patch at level k
    coarse = _renderer(path, gl_context(), levels=3)  # level 3 on the GPU
    with pytest.raises(RenderError, match=r"level 6, .*GPU holds: level 3 of the block"):
        coarse.draw(cam, sel)
    b = tuple(int(v) for v in sel.blocks[sel.block[0]])
    missing = _renderer(path, gl_context(), skip=(b,))
    with pytest.raises(RenderError, match=rf"block \({b[0]}, {b[1]}\), which is not on the GPU"):
        missing.draw(cam, sel)
    outside = dataclasses.replace(sel, col=sel.col + (1 << sel.depth))  # past the block
    with pytest.raises(RenderError, match="is outside what the GPU holds"):
        full.draw(cam, outside)
    full.draw(cam, sel)  # the held selection draws
    for r in (full, coarse, missing):
        r.close()
