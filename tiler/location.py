"""Where a store lives: one place turning a str, Path or zarr ``Store`` into what the tiler needs.

A :class:`Location` answers: does the store exist, remove it, open it as a zarr group, is it a
local directory (and its path), a picklable form for worker processes, renaming where the backend
allows it (local directories), and small raw-key operations (get, put, put-if-absent, delete,
exists, list) used by the lease, the resume journal and the verifier. Three kinds of target:

- a local path (str or ``os.PathLike``): plain file operations;
- an fsspec URL (``memory://``, ``http(s)://``, ``s3://`` ...): the fsspec filesystem of the URL;
- a zarr ``Store`` object: its async API, run on a private event loop per call.

Adding a backend means adding one branch here (see docs/FORMAT.md, "Store backends").
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import shutil
import threading
from collections.abc import Coroutine
from pathlib import Path
from typing import Any, TypeVar

import zarr
from zarr.abc.store import Store
from zarr.buffer import default_buffer_prototype

from tiler.atomic import partial_name, write_atomic
from tiler.errors import BucketNotFoundError, StorageOptionsError, StoreError, StoreURLError
from tiler.remote import is_http
from tiler.s3_reader import S3_READER_ENV, open_s3_reader
from tiler.transport import (
    http_options,
    is_transport_error,
    missing_bucket,
    missing_bucket_message,
    s3fs_options,
    unavailable,
)

T = TypeVar("T")


def is_url(path: str | os.PathLike) -> bool:
    """True for fsspec URLs such as ``memory://``, ``http://``, ``s3://``."""
    return "://" in str(path)


def _run(coro: Coroutine[Any, Any, T]) -> T:
    """Run a coroutine to completion from sync code (own loop; a helper thread if one runs)."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(coro)
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["v"] = asyncio.run(coro)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
            box["e"] = exc

    t = threading.Thread(target=target, name="terrastream-location-io")
    t.start()
    t.join(timeout=600)
    if t.is_alive():
        raise StoreError("a store operation did not finish within 600 s")
    if "e" in box:
        raise box["e"]
    return box["v"]


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


class Location:
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
        _run(self.target.delete_dir(""))

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

    # ---- raw keys ------------------------------------------------------------------------
    def _key_path(self, key: str) -> str:
        if self.is_local:
            return os.path.join(self.target, *key.split("/"))  # type: ignore[arg-type]
        _, path = self._fs()
        return f"{path.rstrip('/')}/{key}"

    def get_bytes(self, key: str) -> bytes | None:
        """The bytes stored under ``key``, or None if it does not exist."""
        if isinstance(self.target, Store):
            buf = _run(self.target.get(key, prototype=default_buffer_prototype()))
            return None if buf is None else buf.to_bytes()
        if self.is_local:
            try:
                with open(self._key_path(key), "rb") as f:
                    return f.read()
            except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
                return None
        fs, _ = self._fs()
        try:
            return fs.cat_file(self._key_path(key))
        except FileNotFoundError:
            return None

    def put_bytes(self, key: str, data: bytes) -> None:
        """Store ``data`` under ``key`` (local: written to a temporary file, then renamed)."""
        if isinstance(self.target, Store):
            buf = default_buffer_prototype().buffer.from_bytes(data)
            _run(self.target.set(key, buf))
            return
        if self.is_local:
            write_atomic(self._key_path(key), data)
            return
        fs, _ = self._fs()
        try:
            fs.pipe_file(self._key_path(key), data)
        except FileNotFoundError as exc:  # (s3fs: the first write into a missing bucket)
            if missing_bucket(exc):
                raise BucketNotFoundError(missing_bucket_message(self.url)) from exc
            raise

    def put_if_absent(self, key: str, data: bytes) -> bool:
        """Create ``key`` only if it does not exist; True if this call created it.

        Atomic for local directories (the whole content appears at once: a temporary file is
        hard-linked into place, so a concurrent reader never sees it empty or half written) and
        zarr Stores that implement ``set_if_not_exists``; best effort (check, then write) for
        fsspec URLs.
        """
        if self.is_local:
            return _link_if_absent(self._key_path(key), data)
        if isinstance(self.target, Store):
            store = self.target
            buf = default_buffer_prototype().buffer.from_bytes(data)

            async def go() -> bool:
                await store.set_if_not_exists(key, buf)
                got = await store.get(key, prototype=default_buffer_prototype())
                return got is not None and got.to_bytes() == data

            return _run(go())
        if self.key_exists(key):
            return False
        self.put_bytes(key, data)
        return self.get_bytes(key) == data

    def delete_key(self, key: str) -> None:
        """Delete ``key`` if it exists."""
        if isinstance(self.target, Store):
            _run(self.target.delete(key))
            return
        if self.is_local:
            with contextlib.suppress(FileNotFoundError):
                os.remove(self._key_path(key))
            return
        fs, _ = self._fs()
        with contextlib.suppress(FileNotFoundError):
            fs.rm_file(self._key_path(key))

    def delete_prefix(self, prefix: str) -> None:
        """Delete every key under ``prefix`` (a zarr array or group path)."""
        if isinstance(self.target, Store):
            _run(self.target.delete_dir(prefix))
            return
        if self.is_local:
            p = self._key_path(prefix)
            if os.path.isdir(p):
                shutil.rmtree(p)
            return
        fs, _ = self._fs()
        p = self._key_path(prefix)
        if fs.exists(p):
            fs.rm(p, recursive=True)

    def key_exists(self, key: str) -> bool:
        """True if ``key`` exists."""
        if isinstance(self.target, Store):
            return bool(_run(self.target.exists(key)))
        if self.is_local:
            return os.path.isfile(self._key_path(key))
        fs, _ = self._fs()
        return self._fs_exists(fs, self._key_path(key), f"key {key!r}")

    def list_keys(self, prefix: str = "") -> list[str]:
        """Every key under ``prefix`` (raises NotImplementedError where listing is impossible)."""
        if isinstance(self.target, Store):
            store = self.target

            async def go() -> list[str]:
                return [k async for k in store.list_prefix(prefix)]

            return _run(go())
        if self.is_local:
            root = self.path
            base = root / prefix if prefix else root
            if not base.exists():
                return []
            return sorted(p.relative_to(root).as_posix() for p in base.rglob("*") if p.is_file())
        if str(self.target).startswith(("http://", "https://")):
            raise NotImplementedError(f"{self.url!r} cannot be listed over HTTP")
        fs, root = self._fs()
        root = root.rstrip("/")
        base = f"{root}/{prefix}" if prefix else root
        if not fs.exists(base):
            return []
        return sorted(p[len(root) + 1 :] for p in fs.find(base))

    @property
    def can_list(self) -> bool:
        """False where the backend cannot list a store's files (plain HTTP), so
        :meth:`total_size` cannot sum them."""
        return not is_http(str(self.target))

    def total_size(self, prefix: str = "") -> int:
        """Total bytes stored under ``prefix`` (0 where the backend cannot list, e.g. HTTP)."""
        if self.is_local:
            base = self.path / prefix if prefix else self.path
            if base.is_file():
                return base.stat().st_size
            return sum(p.stat().st_size for p in base.rglob("*") if p.is_file())
        if isinstance(self.target, Store):
            store = self.target

            async def go() -> int:
                n = 0
                async for key in store.list_prefix(prefix):
                    n += int(await store.getsize(key))
                return n

            try:
                return _run(go())
            except NotImplementedError:
                return 0
        if str(self.target).startswith(("http://", "https://")):
            return 0
        fs, root = self._fs()
        base = f"{root.rstrip('/')}/{prefix}" if prefix else root
        if not fs.exists(base):
            return 0
        return int(sum(d["size"] for d in fs.find(base, detail=True).values()))

    def remove_partial_files(self) -> int:
        """Delete leftover ``*.partial`` temporary files of interrupted writes (local only)."""
        if not self.is_local or not self.path.is_dir():
            return 0
        n = 0
        for p in self.path.rglob("*.partial"):
            p.unlink(missing_ok=True)
            n += 1
        return n

    def change_token(self) -> object:
        """A cheap value that changes when the root metadata is replaced (reader check)."""
        if self.is_local:
            try:
                st = os.stat(self._key_path("zarr.json"))
            except FileNotFoundError:
                return None
            return (st.st_ino, st.st_mtime_ns, st.st_size)
        data = self.get_bytes("zarr.json")
        return None if data is None else hashlib.blake2b(data, digest_size=16).digest()


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


def _link_if_absent(path: str, data: bytes) -> bool:
    """Create the file ``path`` holding ``data`` unless it exists; True if this call made it.

    The bytes go to a private temporary file first, which is then hard-linked to ``path``
    (``link`` fails if ``path`` exists), so the file never exists with partial content. On a
    filesystem without hard links, ``O_EXCL`` creation (content written just after) is used.
    """
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = partial_name(path)
    with open(tmp, "wb") as f:
        f.write(data)
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    except OSError:  # no hard links here (some FUSE or SMB mounts)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return True
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
