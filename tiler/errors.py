"""Errors raised by the tiler. Leaves also inherit the matching built-in type."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


class NamedParams(Exception):
    """An error whose message may name API parameters, which a front end words its own way.

    ``Error(template, params={"overwrite": "overwrite=True"}, **values)``: ``template`` has a
    ``{name}`` field per parameter (worded ``params[name]`` in the Python API) and per value;
    :meth:`message` with ``names`` (the CLI's flags) words the parameters that way (a wording
    may itself hold ``{value}`` fields). Without ``params`` the error is a plain exception."""

    def __init__(
        self, *args: object, params: Mapping[str, str] | None = None, **values: object
    ) -> None:
        self.template = str(args[0]) if params is not None and args else None
        self.params, self.values = dict(params or {}), values
        super().__init__(*((self.message(),) if self.template is not None else args))

    def message(self, names: Mapping[str, str] | None = None) -> str:
        """The message with each parameter worded ``names[name]`` (default: the API's)."""
        if self.template is None:
            return str(self)
        words = {n: (names or {}).get(n, w).format(**self.values) for n, w in self.params.items()}
        return self.template.format(**words, **self.values)

    def __reduce__(self) -> tuple:  # through a worker process: rebuilt from the template
        if self.template is None:
            return super().__reduce__()
        return (_rebuild, (type(self), self.template, self.params, self.values))


def _rebuild(cls: type, template: str, params: dict, values: dict) -> NamedParams:
    return cls(template, params=params, **values)


class TilerError(NamedParams):
    """Root of every error the tiler raises on purpose."""


class LayoutError(TilerError, ValueError):
    """A block size, level or grid shape that the layout does not allow."""


class SourceError(TilerError, ValueError):
    """A source raster that cannot be tiled (missing, unreadable, empty, all nodata...)."""


class SourceNotFoundError(SourceError, FileNotFoundError):
    """The source raster does not exist."""


class HeightRangeError(SourceError):
    """Valid samples beyond any terrain's heights (an undeclared nodata value, other units):
    ``value`` (metres), ``raw`` (the first one as the source holds it, written out),
    ``count`` and the first one's ``row``/``col`` (in its block's window, or in the DEM)."""

    def __init__(self, message: str, *, value: float, raw: str, count: int, row: int, col: int):
        super().__init__(message)
        self.value, self.raw, self.count, self.row, self.col = value, raw, count, row, col

    def __reduce__(self) -> tuple:  # through a worker process
        return (_height_range, (str(self), self.value, self.raw, self.count, self.row, self.col))


def _height_range(msg: str, value: float, raw: str, count: int, row: int, col: int):
    return HeightRangeError(msg, value=value, raw=raw, count=count, row=row, col=col)


class SourceReadError(TilerError, OSError):
    """A source raster that opened but failed to read (truncated, damaged, its server failed)."""


class SourceUnavailableError(SourceReadError):
    """A source behind a URL whose server failed, stopped answering or refused access: fixed
    outside the file, which says nothing about it."""


class StoreError(TilerError, OSError):
    """A store that cannot be written or read as asked."""


class OutputError(TilerError, OSError):
    """An output file (a GeoTIFF written by ``export`` or ``synth``) that could not be written
    whole: nothing is left at its path."""


class StoreExistsError(StoreError, FileExistsError):
    """The destination exists and ``overwrite`` was not given."""


class StoreIncompleteError(StoreError):
    """The store was never finished (an interrupted run); run the same command again."""


class StoreVersionError(StoreError):
    """The store was written by a newer format version than this tool reads."""


class StoreCorruptError(StoreError):
    """The store's metadata or data are damaged or inconsistent."""


class BlockDataError(StoreCorruptError):
    """One block's data in one array is damaged (checksum) or missing; names all three."""

    def __init__(self, message: str, *, array: str, block: tuple[int, int], level: int | None):
        super().__init__(message)
        self.array, self.block, self.level = array, block, level

    def __reduce__(self) -> tuple:  # through a worker process (dask's, multiprocessing's)
        return (_located, (type(self), str(self), self.array, self.block, self.level))


def _located(cls: type, message: str, array: Any, block: Any, level: Any) -> Exception:
    """Rebuild a :class:`BlockDataError` / :class:`StoreUnavailableError` after pickling (its
    keyword-only fields made the default unpickling fail, or drop them)."""
    return cls(message, array=array, block=block, level=level)


class ChunkChecksumError(BlockDataError):
    """A chunk's crc32c does not match its bytes (bit rot, a torn write, tampering)."""


class MissingChunkError(BlockDataError):
    """A chunk the index says was written is absent (deleted or never synced)."""


class StoreUnavailableError(StoreError):
    """The store's server or the network failed a read (timeout, refused or dropped connection,
    an HTTP 5xx or 403): not damage in the store; retrying later may succeed. ``array``,
    ``block`` and ``level`` name what was being read (None when it was not a block)."""

    def __init__(
        self,
        message: str,
        *,
        array: str | None = None,
        block: tuple[int, int] | None = None,
        level: int | None = None,
    ):
        super().__init__(message)
        self.array, self.block, self.level = array, block, level

    def __reduce__(self) -> tuple:  # through a worker process: the block kept
        return (_located, (type(self), str(self), self.array, self.block, self.level))


class StoreChangedError(StoreError):
    """The store was replaced or rewritten while a reader had it open; reopen it."""


class StoreLockedError(StoreError, BlockingIOError):
    """Another process holds the store's writer lease."""


class JobMismatchError(StoreExistsError):
    """An unfinished store was started with another source or other settings."""


class TilingInterrupted(TilerError, KeyboardInterrupt):
    """Tiling was interrupted (Ctrl-C); the store is resumable by rerunning the same call."""


class KernelUnavailableError(TilerError, ImportError):
    """The compiled kernels were required (``TERRASTREAM_KERNELS=numba``) but cannot load."""


class StoreHeightsError(StoreError, ValueError):
    """The store holds values no terrain has (tiled before they were refused): not drawable."""


class GeographicStoreError(StoreError, ValueError):
    """A store whose x/y are degrees (geographic CRS): it cannot be streamed or rendered."""


class RemoteStoreError(StoreError, ConnectionError):
    """A remote store whose server cannot serve what reading a store needs (byte ranges)."""


class BucketNotFoundError(StoreError, FileNotFoundError):
    """The object-store bucket a store URL names does not exist (``s3://no-such-bucket/...``)."""


class StoreURLError(StoreError, ValueError):
    """A store URL that cannot address the store's keys (an http(s) URL with a query string
    or fragment): a usage error."""


class StorageOptionsError(TilerError, ValueError):
    """Storage options that are not a JSON object, or given for a non-URL location."""


class SchedulerError(TilerError, ValueError):
    """A scheduler spec that is not threads/processes/dask/an address, or one not reachable."""


class BlockFailedError(TilerError, RuntimeError):
    """A block's task failed on every retry (``.block`` is its ``(row, col)``)."""

    def __init__(self, message: str, block: tuple[int, int] | None = None) -> None:
        super().__init__(message)
        self.block = block

    def __reduce__(self) -> tuple:  # through a worker process: the block kept
        return (type(self), (str(self), self.block))
