"""Fixtures of the renderer's tests: one headless GL context for the whole run, checked for GL
errors before and after every ``gl``-marked test (as moderngl's own tests do), and a renderer
factory on it.

Without a GL context a GL test module is skipped with the reason on a user's machine; with
``CI=true`` (the project's CI machine always has EGL + Mesa) it fails with the reason instead, so
CI cannot be green with every GL test skipped.

This file shadows ``tests/conftest.py`` as the module ``conftest`` for the tests below it, so it
re-exports that file's helpers (``from conftest import fractal`` keeps working everywhere).
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "_terrastream_tests_conftest", Path(__file__).resolve().parents[1] / "conftest.py"
)
assert _spec is not None and _spec.loader is not None
_root = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_root)
SHARED_DATA = _root.SHARED_DATA
fractal = _root.fractal
shared_file = _root.shared_file
write_dem = _root.write_dem

_CONTEXT: list = []  # the process's one context, made on first use


def on_ci() -> bool:
    """``CI`` is set to a true value (``true``, ``1``, ``yes``)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def gl_context():
    """The shared headless EGL context. Without one: skip the calling module with the reason,
    or with ``CI=true`` fail it (``pytest.fail``) with the reason."""
    if not _CONTEXT:
        from render.errors import GLUnavailableError
        from render.gpu import create_context

        try:
            _CONTEXT.append(create_context())
        except GLUnavailableError as exc:
            reason = f"no headless OpenGL 4.5 context: {exc}"
            if on_ci():
                pytest.fail(f"{reason} (CI=true: GL tests must run on CI)", pytrace=False)
            pytest.skip(reason, allow_module_level=True)
    return _CONTEXT[0]


def make_current(c):
    """Make ``c`` the current context and leave it so (code under test, e.g. the CLI, may have
    made its own context current; ``with ctx`` would restore that one on exit)."""
    c.__enter__()
    return c


@pytest.fixture(scope="session")
def ctx():
    """The shared GL context (see :func:`gl_context`)."""
    return gl_context()


def check_no_gl_error(c, when: str) -> None:
    """Fail the test if ``c.error`` (moderngl: the pending GL error) is not ``GL_NO_ERROR``."""
    err = c.error
    if err != "GL_NO_ERROR":
        pytest.fail(f"OpenGL error {err} {when}", pytrace=False)


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
