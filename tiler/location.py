"""Where a store lives: one place turning a str, Path or zarr ``Store`` into what the tiler needs.

A :class:`Location` answers: does the store exist, remove it, open it as a zarr group, is it a
local directory (and its path), a picklable form for worker processes, renaming where the backend
allows it (local directories), and small raw-key operations (get, put, put-if-absent, delete,
exists, list) used by the lease, the resume journal and the verifier. Three kinds of target:

- a local path (str or ``os.PathLike``): plain file operations;
- an fsspec URL (``memory://``, ``http(s)://``, ``s3://`` ...): the fsspec filesystem of the URL;
- a zarr ``Store`` object: its async API, run on a private event loop per call.

The raw-key operations are :class:`tiler.location_keys.LocationKeys`, which :class:`Location`
inherits. Adding a backend means adding one branch here (opening it, whether it can rename) and
one in :mod:`tiler.location_keys` (its key operations; see docs/FORMAT.md, "Store backends").
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import zarr
from zarr.abc.store import Store

from tiler.errors import StorageOptionsError, StoreError, StoreURLError
from tiler.location_keys import LocationKeys, run_sync
from tiler.remote import is_http
from tiler.s3_reader import S3_READER_ENV, open_s3_reader
from tiler.transport import http_options, is_transport_error, s3fs_options, unavailable


def is_url(path: str | os.PathLike) -> bool:
    """True for fsspec URLs such as ``memory://``, ``http://``, ``s3://``."""
    return "://" in str(path)


def parse_storage_options(text: str | None) -> dict[str, Any] | None:
    """A ``storage_options`` dict from JSON text (None/empty → None); raises ValueError."""
    if text is None or not str(text).strip():
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise StorageOptionsError(
            f'storage options must be a JSON object, e.g. \'{{"endpoint_url": '
            f'"http://127.0.0.1:9000"}}\'; got {text!r} ({exc.msg})'
        ) from exc
    if not isinstance(value, dict):
        raise StorageOptionsError(
            f"storage options must be a JSON object (key: value), got {type(value).__name__}: "
            f"{text!r}"
        )
    return value


class Location(LocationKeys):
    """A store location: local directory, fsspec URL or zarr ``Store`` object.

    ``storage_options`` (fsspec URLs only) go to the URL's filesystem, e.g.
    ``{"endpoint_url": "http://127.0.0.1:9000", "key": ..., "secret": ...}`` for ``s3://``;
    without them fsspec's defaults apply (for S3: ``AWS_*`` environment variables, profiles).
    """

    def __init__(
        self,
        target: str | os.PathLike | Store | Location,
        storage_options: dict[str, Any] | None = None,
        *,
        writing: bool = False,
    ) -> None:
        shown: str | None = None
        if isinstance(target, Location):
            storage_options = storage_options or target.storage_options
            writing = writing or target.writing
            shown = target._shown
            target = target.target
        #: a store being written (:func:`for_writing`): ``s3://`` clients keep more tries
        self.writing = writing
        self.storage_options: dict[str, Any] | None = dict(storage_options or {}) or None
        self.target: str | Store
        if isinstance(target, Store):
            self.target = target
        elif isinstance(target, str | os.PathLike):
            self.target = str(target)
            if not is_url(self.target) and not self.target.startswith("memory:"):
                # a local path is kept absolute (a later os.chdir would read another
                # directory), and shown as it was given
                shown = shown or self.target
                self.target = os.path.abspath(self.target)
        else:
            raise StoreError(
                f"a store location must be a path, a URL or a zarr Store, got {type(target)!r}"
            )
        #: the path as the caller gave it (messages), for a local target
        self._shown = shown
        if isinstance(self.target, str) and is_http(self.target):
            _refuse_query(self.target)
        if self.storage_options and not (isinstance(self.target, str) and is_url(self.target)):
            raise StorageOptionsError(
                f"storage options apply to URLs (s3://, gs://, http://...), not to {self.url!r}; "
                "drop them for a local path or a zarr Store object"
            )
        self.fsspec_options()  # a bad `timeout` is refused here, before anything runs

    # ---- identity ------------------------------------------------------------------------
    @property
    def url(self) -> str:
        """A display string: the path (as given) or URL, or the Store's repr."""
        if self._shown is not None:
            return self._shown
        return self.target if isinstance(self.target, str) else repr(self.target)

    def __repr__(self) -> str:
        return f"Location({self.url!r})"

    def __str__(self) -> str:
        return self.url

    @property
    def is_local(self) -> bool:
        """True for a local directory path."""
        return isinstance(self.target, str) and not is_url(self.target)

    @property
    def is_memory(self) -> bool:
        """True for process-local memory (``memory://`` or a zarr ``MemoryStore``)."""
        if isinstance(self.target, str):
            return self.target.startswith("memory:")
        return isinstance(self.target, zarr.storage.MemoryStore)

    @property
    def path(self) -> Path:
        """The local directory (raises for other kinds)."""
        if not self.is_local:
            raise StoreError(f"{self.url!r} is not a local directory")
        return Path(self.target)  # type: ignore[arg-type]

    def for_workers(self) -> Location:
        """A copy worker processes or dask workers can unpickle and reopen (URL + options)."""
        self.picklable()
        return Location(self.target, self.storage_options, writing=self.writing)

    def picklable(self) -> str:
        """A form worker processes can reopen (a path or URL); raises for memory and objects."""
        if not isinstance(self.target, str) or self.is_memory:
            raise StoreError(f"{self.url!r} cannot be shared with worker processes")
        return self.target

    @property
    def can_share_with_processes(self) -> bool:
        """Whether separate processes can open this location."""
        return isinstance(self.target, str) and not self.is_memory

    @property
    def can_rename(self) -> bool:
        """Whether :meth:`rename_to` is atomic here (local directories)."""
        return self.is_local

    # ---- whole-store operations ----------------------------------------------------------
    def fsspec_options(self) -> dict[str, Any]:
        """The options fsspec gets: ``http(s)://`` adds read timeouts, ``s3://`` bounds
        botocore's retries (:mod:`tiler.transport`)."""
        if isinstance(self.target, str) and self.target.startswith(("http://", "https://")):
            return http_options(self.storage_options)
        if isinstance(self.target, str) and self.target.startswith("s3://"):
            return s3fs_options(self.storage_options)
        return dict(self.storage_options or {})

    @property
    def is_s3(self) -> bool:
        """True for an ``s3://`` URL (opened through s3fs, with :mod:`tiler._s3fs`'s tries)."""
        return isinstance(self.target, str) and self.target.startswith("s3://")

    def zarr_args(self, mode: str = "r") -> tuple[Any, dict[str, Any]]:
        """``(store, kwargs)`` for zarr's ``open_*`` functions: the target with its fsspec
        options, or for ``s3://`` an ``FsspecStore`` over :func:`tiler._s3fs.s3fs_filesystem`
        (the tries of a writer when this location is :attr:`writing` or ``mode`` writes)."""
        so = self.fsspec_options()
        if self.is_s3:
            from zarr.storage import FsspecStore

            from tiler._s3fs import s3fs_filesystem

            fs = s3fs_filesystem(so, write=self.writing or mode != "r", asynchronous=True)
            path = fs._strip_protocol(self.target)
            return FsspecStore(fs, path=path, read_only=mode == "r"), {}
        return self.target, {"storage_options": so} if so else {}

    def open_group(self, mode: str = "r", **kwargs: Any) -> zarr.Group:
        """Open the root zarr group (``kwargs`` go to ``zarr.open_group``).

        Reading an ``s3://`` store goes through obstore where installed (faster than s3fs,
        see docs; ``TERRASTREAM_S3_READER=fsspec`` to opt out); writes always use fsspec.
        """
        if (
            mode == "r"
            and isinstance(self.target, str)
            and self.target.startswith("s3://")
            and os.environ.get(S3_READER_ENV, "obstore") != "fsspec"
        ):
            reader = open_s3_reader(self.target, self.storage_options)
            if reader is not None:
                return zarr.open_group(reader, mode="r", **kwargs)
        store, kw = self.zarr_args(mode)
        return zarr.open_group(store, mode=mode, **kw, **kwargs)

    def open_array(self, path: str, mode: str = "r") -> zarr.Array:
        """Open the array at ``path`` inside the store."""
        store, kw = self.zarr_args(mode)
        return zarr.open_array(store, path=path, mode=mode, **kw)

    def _fs(self) -> tuple[Any, str]:
        if self.is_s3:
            from tiler._s3fs import s3fs_filesystem

            fs = s3fs_filesystem(self.fsspec_options(), write=self.writing)
            return fs, fs._strip_protocol(self.target)
        import fsspec

        return fsspec.core.url_to_fs(self.target, **self.fsspec_options())

    def exists(self) -> bool:
        """True if anything is stored at this location."""
        if self.is_local:
            return os.path.exists(self.target)  # type: ignore[arg-type]
        if isinstance(self.target, str):
            fs, path = self._fs()
            return self._fs_exists(fs, path, "the store")
        return self.key_exists("zarr.json")

    def _fs_exists(self, fs: Any, path: str, subject: str) -> bool:
        """Whether ``path`` exists on ``fs``. Over http(s) only an HTTP 404 (or 410) says no:
        fsspec's plain ``exists`` says no to any status >= 400 and any connection failure, so
        a transient 503 read as a missing chunk, damage; a server's or the network's failure
        is :func:`~tiler.transport.unavailable`'s :class:`StoreUnavailableError` instead.
        (s3fs's ``exists`` already raises such failures as they are, which callers classify.)"""
        if not is_http(str(self.target)):
            return bool(fs.exists(path))
        try:
            return bool(fs.exists(path, strict=True))
        except FileNotFoundError:
            return False
        except Exception as exc:
            if not is_transport_error(exc):
                raise
            raise unavailable(f"whether {subject} exists", self.url, exc) from exc

    def remove(self) -> None:
        """Remove everything stored at this location (no checks: callers decide)."""
        if self.is_local:
            p = self.path
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
            return
        if isinstance(self.target, str):
            fs, path = self._fs()
            if fs.exists(path):
                fs.rm(path, recursive=True)
            return
        run_sync(self.target.delete_dir(""))

    def sibling(self, suffix: str) -> Location:
        """A new local location next to this one (``<path><suffix>``)."""
        return Location(str(self.path) + suffix)

    def rename_to(self, other: Location) -> None:
        """Atomically rename this local directory to ``other`` (which must not exist)."""
        if not (self.is_local and other.is_local):
            raise StoreError(f"cannot rename {self.url!r}: only local directories can be renamed")
        os.rename(self.path, other.path)

    def parent_writable(self) -> str | None:
        """For a local path: None if its parent is a writable directory, else that parent."""
        if not self.is_local:
            return None
        parent = os.path.dirname(os.path.abspath(self.target))  # type: ignore[arg-type]
        if os.path.isdir(parent) and os.access(parent, os.W_OK):
            return None
        return parent


def _refuse_query(url: str) -> None:
    """Refuse an http(s) store URL with a query string or fragment: each key's URL is the
    store's URL with ``/<key>`` appended, so a token there (``?sig=...``) would reach the
    server as part of the last value (``?sig=1/zarr.json``) and be refused as wrong."""
    if "?" not in url and "#" not in url:
        return
    what = "a query string" if "?" in url else "a fragment (#...)"
    raise StoreURLError(
        f"the store URL {url!r} has {what}, which cannot be carried to each of the store's "
        "keys (each is read at <store URL>/<key>); give the store's URL without it, and pass a "
        "token as a header instead: --storage-options "
        '\'{"headers": {"Authorization": "Bearer ..."}}\' (or '
        '{"client_kwargs": {"headers": {...}}}; storage_options= in the Python API)'
    )


def as_location(
    target: str | os.PathLike | Store | Location, storage_options: dict[str, Any] | None = None
) -> Location:
    """The :class:`Location` of a path, URL, zarr Store or Location (with storage options)."""
    if isinstance(target, Location) and not storage_options:
        return target
    return Location(target, storage_options)


def for_writing(loc: Location) -> Location:
    """``loc`` with the client retries of a store being written (``s3://``: botocore's
    :data:`~tiler.transport.S3FS_WRITE_RETRIES` unless set; others as they are). An
    ``http(s)://`` store is read-only: :class:`StoreError` saying where to write instead."""
    if not loc.can_list:
        raise StoreError(
            f"{loc.url!r} is an http(s) store, which is read-only here: tile (or --repair) a "
            "local directory or an object store (s3://...) and serve that"
        )
    if not loc.is_s3:
        return loc
    return Location(loc.target, s3fs_options(loc.storage_options, write=True), writing=True)
