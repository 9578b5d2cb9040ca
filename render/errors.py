"""Errors of the renderer; the root :class:`RenderError` maps to exit status 2 in the CLI.
Messages carry the values and advice, never a CLI flag name (the CLI adds those)."""

from __future__ import annotations

from collections.abc import Mapping


class RenderError(Exception):
    """Root of the renderer's errors (messages are meant for the user)."""


class GLUnavailableError(RenderError, RuntimeError):
    """No headless OpenGL 4.5 context could be created (EGL / Mesa missing)."""


class GLStateError(RenderError, RuntimeError):
    """OpenGL reported an error, or a shader failed to build."""


class SelectionError(RenderError, ValueError):
    """Invalid input to patch selection or stitching."""


class EmptyViewError(RenderError, ValueError):
    """A measured view holds no terrain sample: its figures would be vacuous."""


class CameraSpecError(RenderError, ValueError):
    """A camera description cannot be built (:func:`render.views.make_camera`).

    The message names the offending parameters by their Python names (``position``,
    ``look_at``, ``yaw``, ``pitch``); a front end that calls them something else (the CLI's
    flags) gets its own wording from :meth:`message` (``params`` lists the names used)."""

    def __init__(self, template: str, **values: object) -> None:
        self.template = template
        self.values = values
        self.params = tuple(n for n in CAMERA_PARAMS if "{" + n + "}" in template)
        super().__init__(self.message())

    def message(self, names: Mapping[str, str] | None = None) -> str:
        """The message with each parameter called ``names[param]`` (default: its own name)."""
        names = names or {}
        return self.template.format(**{n: names.get(n, n) for n in CAMERA_PARAMS}, **self.values)


#: the parameters of :func:`render.views.make_camera` a :class:`CameraSpecError` may name
CAMERA_PARAMS = ("position", "look_at", "yaw", "pitch")
