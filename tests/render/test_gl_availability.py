"""The GL context fixture's rule (no GL needed): skip with the reason on a user's machine, fail
with the reason when ``CI=true``; and the GL-error check fires on a pending error."""

from __future__ import annotations

import pytest
import shared_gl

from render import gpu
from render.errors import GLUnavailableError


@pytest.fixture
def no_gl(monkeypatch):
    def broken():
        raise GLUnavailableError("cannot create a headless OpenGL 4.5 context through EGL: test")

    monkeypatch.setattr(shared_gl, "_CONTEXT", [])
    monkeypatch.setattr(gpu, "create_context", broken)


@pytest.mark.parametrize("value", ["true", "1", "TRUE"])
def test_missing_gl_fails_on_ci(no_gl, monkeypatch, value):
    monkeypatch.setenv("CI", value)
    with pytest.raises(pytest.fail.Exception, match="no headless OpenGL 4.5 context.*CI=true"):
        shared_gl.gl_context()


@pytest.mark.parametrize("value", [None, "", "false", "0"])
def test_missing_gl_skips_with_the_reason_elsewhere(no_gl, monkeypatch, value):
    if value is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", value)
    with pytest.raises(pytest.skip.Exception, match="no headless OpenGL 4.5 context: cannot"):
        shared_gl.gl_context()


def test_the_context_is_made_once(monkeypatch):
    made = []
    monkeypatch.setattr(shared_gl, "_CONTEXT", [])
    monkeypatch.setattr(gpu, "create_context", lambda: made.append(object()) or made[-1])
    assert shared_gl.gl_context() is shared_gl.gl_context()
    assert len(made) == 1


class _FakeContext:
    def __init__(self, error: str) -> None:
        self.error = error


def test_gl_error_check_fires_on_a_pending_error():
    shared_gl.check_no_gl_error(_FakeContext("GL_NO_ERROR"), "quiet")
    with pytest.raises(pytest.fail.Exception, match="OpenGL error GL_INVALID_ENUM left by"):
        shared_gl.check_no_gl_error(_FakeContext("GL_INVALID_ENUM"), "left by the test")
