"""Errors raised by the streamer. Leaves also inherit the matching built-in type."""

from __future__ import annotations

from typing import Any

from tiler.errors import NamedParams


class StreamerError(NamedParams):
    """Root of every error the streamer raises on purpose."""


class CameraError(StreamerError, ValueError):
    """A camera pose, field of view, viewport or clipping range that is not valid."""


class PathError(StreamerError, ValueError):
    """A fly-through path that cannot be built as asked (bad frame count, bounds, speed...)."""


class KeyframeError(PathError):
    """A keyframe file that is malformed (missing columns, unsorted or non-finite values)."""


class PathOutOfViewError(PathError):
    """A camera path none of whose frames sees the DEM: its figures and frames would be vacuous."""


class FrustumError(StreamerError, ValueError):
    """A polygon, frame rate, extension length or culling mode that is not valid."""


class LodError(StreamerError, ValueError):
    """An LOD request that is not valid (threshold, patch size, error field, metric name...)."""


class BudgetError(StreamerError, ValueError):
    """A cache byte budget that is not valid, or too small for what the view needs."""


class LoadError(StreamerError, OSError):
    """A block level that could not be read after every retry."""

    @classmethod
    def after_retries(
        cls, block: tuple[int, int], exc: BaseException, retries: int, heal: bool, frame: Any
    ) -> LoadError:
        """The error a session raises once for ``block`` (``frame``: the frame it ends)."""
        err = cls(
            f"block {block} could not be read after {retries} tries: {exc}; it stays at the "
            "level it has" + (" and is retried while it is needed" if heal else "")
        )
        err.frame = frame  # type: ignore[attr-defined]
        return err


class SessionClosedError(StreamerError, RuntimeError):
    """The session was used after :meth:`Session.close`."""


class SessionThreadError(StreamerError, RuntimeError):
    """:meth:`Session.update` was called while another thread was inside it (one caller
    thread drives a session: its frame state is not shared)."""
