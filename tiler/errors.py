"""Errors raised by the tiler. Leaves also inherit the matching built-in type."""

from __future__ import annotations


class TilerError(Exception):
    """Root of every error the tiler raises on purpose."""


class LayoutError(TilerError, ValueError):
    """A block size, level or grid shape that the layout does not allow."""


class SourceError(TilerError, ValueError):
    """A source raster that cannot be tiled (missing, unreadable, empty, all nodata...)."""


class SourceNotFoundError(SourceError, FileNotFoundError):
    """The source raster does not exist."""


class StoreError(TilerError, OSError):
    """A store that cannot be written or read as asked."""


class StoreExistsError(StoreError, FileExistsError):
    """The destination exists and ``overwrite`` was not given."""


class StoreIncompleteError(StoreError):
    """The store was never finished (an interrupted run); run the same command again."""


class StoreVersionError(StoreError):
    """The store was written by a newer format version than this tool reads."""


class StoreCorruptError(StoreError):
    """The store's metadata or data are damaged or inconsistent."""


class GeographicStoreError(StoreError, ValueError):
    """A store whose x/y are degrees (geographic CRS): it cannot be streamed or rendered."""


class RemoteStoreError(StoreError, ConnectionError):
    """A remote store whose server cannot serve what reading a store needs (byte ranges)."""
