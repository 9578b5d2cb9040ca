"""s3fs filesystems with terrastream's own try counts (imported only where s3fs is used):
:func:`s3fs_filesystem`.

s3fs tries each request ``retries`` times (a class attribute, 5, not a storage option) around
botocore's attempts. These subclasses read the count from :mod:`tiler.transport` when a request
is made; being classes of their own, their instances are cached apart from plain
``S3FileSystem``'s and from each other's (in its cache: clearing it clears them), and they
pickle by name like it.
"""

from __future__ import annotations

import atexit
import contextlib
import weakref
from typing import Any

import s3fs

from tiler import transport


class ReadS3FileSystem(s3fs.S3FileSystem):
    """``S3FileSystem`` trying each request :data:`tiler.transport.S3FS_TRIES` times."""

    @property
    def retries(self) -> int:  # type: ignore[override]
        """s3fs's own tries of a request."""
        return transport.S3FS_TRIES


class WriteS3FileSystem(s3fs.S3FileSystem):
    """``S3FileSystem`` trying each request :data:`tiler.transport.S3FS_WRITE_TRIES` times."""

    @property
    def retries(self) -> int:  # type: ignore[override]
        """s3fs's own tries of a request."""
        return transport.S3FS_WRITE_TRIES


# One instance cache with S3FileSystem's (the class is part of each instance's key), so that
# ``s3fs.S3FileSystem.clear_instance_cache()`` (after the endpoint or credentials in the
# environment changed: they are not part of the key) clears these too.
ReadS3FileSystem._cache = WriteS3FileSystem._cache = s3fs.S3FileSystem._cache


def s3fs_filesystem(
    options: dict[str, Any] | None, *, write: bool = False, asynchronous: bool = False
) -> s3fs.S3FileSystem:
    """The s3fs filesystem for ``options`` (fsspec options: :func:`tiler.transport.s3fs_options`
    already applied) trying each request :data:`~tiler.transport.S3FS_TRIES` times
    (:data:`~tiler.transport.S3FS_WRITE_TRIES` with ``write``)."""
    cls = WriteS3FileSystem if write else ReadS3FileSystem
    fs = cls(asynchronous=asynchronous, **(options or {}))
    if asynchronous:
        _ASYNC.add(fs)
    return fs


#: the asynchronous filesystems made here (zarr's stores run them on zarr's event loop)
_ASYNC: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def close_sessions() -> None:
    """Close the S3 clients of the asynchronous filesystems on zarr's loop, before exit. s3fs
    registers no finalizer for asynchronous instances, so every command that wrote to S3 ended
    with aiohttp's "ERROR asyncio: Unclosed client session" logged at exit."""
    creators = [c for c in (getattr(fs, "_s3creator", None) for fs in list(_ASYNC)) if c]
    if not creators:
        return
    from zarr.core.sync import sync

    for creator in creators:
        with contextlib.suppress(Exception):  # (at exit: a loop or client already gone)
            sync(creator.__aexit__(None, None, None), timeout=5.0)
