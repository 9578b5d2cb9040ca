"""What a failed store read is, in words a user can act on: the store's damage (verify and
repair it) or the server's failure (:mod:`tiler.transport`); pure, no I/O."""

from __future__ import annotations

import numpy as np
import zarr.errors

from tiler.errors import (
    BlockDataError,
    ChunkChecksumError,
    MissingChunkError,
    StoreCorruptError,
    StoreError,
)
from tiler.transport import is_transport_error, unavailable

#: what reading a chunk can raise for a damaged chunk (anything else is not the data's fault)
READ_ERRORS = (ValueError, OSError, RuntimeError)
#: a metadata document that is valid JSON but not an object fails inside zarr's parsing
META_ERRORS = (*READ_ERRORS, AttributeError, TypeError)


def open_error(url: str, name: str, exc: BaseException) -> StoreError | None:
    """The error opening array ``name`` of the store at ``url`` failed with, as the store's
    damage or the server's failure; ``None`` when ``exc`` is neither (raise it as it is)."""
    if is_transport_error(exc):
        return unavailable(f"the metadata of array {name!r}", url, exc, array=name)
    if isinstance(exc, (KeyError, zarr.errors.ArrayNotFoundError)):
        return StoreCorruptError(
            f"store {url!r} has no array {name!r}: the store is damaged; "
            "tile the DEM again (or repair the store)"
        )
    if isinstance(exc, META_ERRORS):
        return StoreCorruptError(f"the metadata of array {name!r} in {url!r} is damaged: {exc}")
    return None


#: what a read raises when the interpreter or its I/O loop is shutting down under it (a
#: program that ended without closing its session): not the data's fault
_SHUTDOWN = ("after shutdown", "after interpreter shutdown", "event loop is closed")


def is_shutdown_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a read cut short by the interpreter's or the I/O loop's shutdown."""
    return isinstance(exc, RuntimeError) and any(t in str(exc).lower() for t in _SHUTDOWN)


def read_error(
    url: str, name: str, block: tuple[int, int], level: int | None, exc: BaseException
) -> StoreError | None:
    """The error reading ``block`` of array ``name`` (``level``: which level, for level
    arrays) failed with: the server's failure, a checksum mismatch or other damage naming the
    block; ``None`` when ``exc`` is none of these (a bug: raise it as it is)."""
    what = f"level {level}" if level is not None else name
    if is_transport_error(exc):
        subject = f"{what} of block {block} (array {name!r})"
        return unavailable(subject, url, exc, array=name, block=block, level=level)
    if not isinstance(exc, READ_ERRORS):
        return None
    if is_shutdown_error(exc):
        return StoreError(
            f"reading {what} of block {block} (array {name!r}) from {url!r} was cut short: "
            f"the program was shutting down ({exc}), not the store's damage; close the "
            "session (or use `with open_session(...)`) before the program ends",
        )
    cls = ChunkChecksumError if "checksum" in str(exc) else BlockDataError
    return cls(
        f"cannot read {what} of block {block} (array {name!r}) from {url!r}: {exc}; "
        "the store is damaged: verify it and repair it from the source",
        array=name,
        block=block,
        level=level,
    )


def is_fill(name: str, out: np.ndarray, fill: int | None, has_nodata: bool) -> bool:
    """Whether a block's values that zarr read from array ``name`` are what zarr gives for an
    absent chunk (its fill: a level's ``fill``, NaN errors, an all-True mask of a block with
    nodata, which writes one): then only the chunk's key can tell."""
    if name.startswith("levels/"):
        return bool(np.all(out == fill))
    if name == "errors":
        return bool(np.all(np.isnan(out)))
    return name == "mask" and has_nodata and bool(out.all())


def missing_chunk(
    url: str, what: str, name: str, block: tuple[int, int], level: int | None
) -> MissingChunkError:
    """A chunk the index says was written is absent (``what``: e.g. ``"level 3"``)."""
    return MissingChunkError(
        f"{what} of block {block} (array {name!r}) is missing from {url!r} although "
        "the store says it was written; the store is damaged: verify it and repair it "
        "from the source",
        array=name,
        block=block,
        level=level,
    )
