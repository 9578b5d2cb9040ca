"""Errors of the renderer; the root :class:`RenderError` maps to exit status 2 in the CLI."""

from __future__ import annotations


class RenderError(Exception):
    """Root of the renderer's errors (messages are meant for the user)."""


class GLUnavailableError(RenderError, RuntimeError):
    """No headless OpenGL 4.5 context could be created (EGL / Mesa missing)."""


class GLStateError(RenderError, RuntimeError):
    """OpenGL reported an error, or a shader failed to build."""


class SelectionError(RenderError, ValueError):
    """Invalid input to patch selection or stitching."""


class CameraSpecError(RenderError, ValueError):
    """A camera given on the command line cannot be built."""
