"""Fixtures of the renderer's tests: one headless GL context for the whole run, checked for GL
errors before and after every ``gl``-marked test (as moderngl's own tests do), and a renderer
factory on it.

Without a GL context a GL test module is skipped with the reason on a user's machine; with
``CI=true`` (the project's CI machine always has EGL + Mesa) it fails with the reason instead, so
CI cannot be green with every GL test skipped.

The context and the error check live in ``shared_gl``, the DEM helpers in ``demtools``
(plainly named modules: this file and ``tests/conftest.py`` are both ``conftest``).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
from shared_gl import check_no_gl_error, gl_context, make_current


@pytest.fixture(scope="session")
def ctx():
    """The shared GL context (see :func:`gl_context`)."""
    return gl_context()


@pytest.fixture(scope="module", autouse=True)
def _gl_current(request):
    """For modules of ``gl`` tests: the shared context is current while their module-scoped
    fixtures are made (autouse fixtures come first within a scope)."""
    marks = getattr(request.module, "pytestmark", [])
    marks = marks if isinstance(marks, list) else [marks]
    if not any(m.name == "gl" for m in marks):
        yield
        return
    make_current(gl_context())
    yield


@pytest.fixture(autouse=True)
def _gl_errors(request):
    """For ``gl``-marked tests: the shared context is current, no GL error is pending before
    the test and none after it."""
    if request.node.get_closest_marker("gl") is None:
        yield
        return
    c = make_current(gl_context())
    check_no_gl_error(c, "pending before the test")
    yield
    check_no_gl_error(c, "left by the test")


@pytest.fixture
def make_renderer(ctx) -> Callable:
    """``make_renderer(store_or_path, size=(128, 96), patch_log2=2, resident=None)``: a
    :class:`render.renderer.TerrainRenderer` on the shared context with every block uploaded
    (up to ``resident[block]`` when given, else full resolution)."""
    from render.renderer import RenderConfig, TerrainRenderer
    from tiler.store import TerrainStore, open_store

    made = []

    def make(store, size=(128, 96), patch_log2: int = 2, resident: dict | None = None):
        s = store if isinstance(store, TerrainStore) else open_store(store)
        r = TerrainRenderer(s, RenderConfig(size=size, patch_log2=patch_log2), ctx=ctx)
        for b in s.blocks():
            r.upload(b, s.read_levels(b, s.k if resident is None else resident[b]))
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()
