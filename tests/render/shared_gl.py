"""The renderer tests' headless GL context and GL error check (used by tests/render/conftest.py
and by test modules: ``from shared_gl import gl_context``; a plainly named module, so that no
test imports a ``conftest`` by name).

Without a GL context a GL test module is skipped with the reason on a user's machine; with
``CI=true`` (the project's CI machine always has EGL + Mesa) it fails with the reason instead, so
CI cannot be green with every GL test skipped.
"""

from __future__ import annotations

import os

import pytest

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


def check_no_gl_error(c, when: str) -> None:
    """Fail the test if ``c.error`` (moderngl: the pending GL error) is not ``GL_NO_ERROR``."""
    err = c.error
    if err != "GL_NO_ERROR":
        pytest.fail(f"OpenGL error {err} {when}", pytrace=False)
