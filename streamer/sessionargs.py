"""The checks of a session's call arguments: the camera, the time step and a wait's timeout
(a bad value is named where it is passed, not deep inside the planner or a wait)."""

from __future__ import annotations

import math

from streamer.camera import Camera
from streamer.errors import CameraError, StreamerError


def check_camera(camera: object) -> None:
    """A :class:`CameraError` unless ``camera`` is a :class:`Camera` (None gave an
    AttributeError about ``pitch`` from deep inside the planner)."""
    if not isinstance(camera, Camera):
        raise CameraError(f"a session needs a streamer.camera.Camera, got {camera!r}")


def check_dt(dt: float | None) -> float | None:
    """``dt`` as a float (None stays None), or :class:`CameraError` unless it is a finite
    number of seconds >= 0 (0: the same instant, no velocity)."""
    if dt is None:
        return None
    try:
        value = float(dt)
    except (TypeError, ValueError):
        raise CameraError(f"dt must be a number of seconds, got {dt!r}") from None
    if not (math.isfinite(value) and value >= 0.0):
        raise CameraError(f"dt must be a finite number of seconds >= 0, got {dt!r}")
    return value


def check_timeout(timeout_s: float | None) -> None:
    """A :class:`StreamerError` unless ``timeout_s`` is None (the session's
    ``wait_timeout_s``) or a finite number of seconds > 0."""
    if timeout_s is not None and not (
        isinstance(timeout_s, (int, float)) and not isinstance(timeout_s, bool)
        and 0 < timeout_s < math.inf
    ):  # fmt: skip
        raise StreamerError(
            f"timeout_s must be a finite number of seconds > 0 (None: the session's "
            f"wait_timeout_s), got {timeout_s!r}"
        )
