"""A :class:`tiler.location.Location`'s raw keys: :class:`LocationKeys`, the small key operations
(get, put, put-if-absent, delete, exists, list, sizes, the change token) the lease, the resume
journal, the verifier and the reader use, one branch per kind of target (a zarr ``Store``
object, a local directory, an fsspec URL); with :func:`run_sync`, which runs a zarr ``Store``'s
async API from sync code, and :func:`link_if_absent`, a local file's atomic create.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import shutil
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

from zarr.abc.store import Store
from zarr.buffer import default_buffer_prototype

from tiler.atomic import partial_name, write_atomic
from tiler.errors import BucketNotFoundError, StoreError
from tiler.remote import is_http
from tiler.transport import missing_bucket, missing_bucket_message

T = TypeVar("T")


def run_sync(coro: Coroutine[Any, Any, T]) -> T:
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


class LocationKeys:
    """The raw-key operations of :class:`tiler.location.Location` (its only user, which sets
    ``target`` and provides ``url``, ``is_local``, ``is_memory``, ``is_s3``, ``path``, ``_fs``
    and ``_fs_exists``)."""

    target: str | Store

    def _key_path(self, key: str) -> str:
        if self.is_local:
            return os.path.join(self.target, *key.split("/"))  # type: ignore[arg-type]
        _, path = self._fs()
        return f"{path.rstrip('/')}/{key}"

    def get_bytes(self, key: str) -> bytes | None:
        """The bytes stored under ``key``, or None if it does not exist."""
        if isinstance(self.target, Store):
            buf = run_sync(self.target.get(key, prototype=default_buffer_prototype()))
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
            run_sync(self.target.set(key, buf))
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
            return link_if_absent(self._key_path(key), data)
        if isinstance(self.target, Store):
            store = self.target
            buf = default_buffer_prototype().buffer.from_bytes(data)

            async def go() -> bool:
                await store.set_if_not_exists(key, buf)
                got = await store.get(key, prototype=default_buffer_prototype())
                return got is not None and got.to_bytes() == data

            return run_sync(go())
        if self.key_exists(key):
            return False
        self.put_bytes(key, data)
        return self.get_bytes(key) == data

    def delete_key(self, key: str) -> None:
        """Delete ``key`` if it exists."""
        if isinstance(self.target, Store):
            run_sync(self.target.delete(key))
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
            run_sync(self.target.delete_dir(prefix))
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
            return bool(run_sync(self.target.exists(key)))
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

            return run_sync(go())
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
                return run_sync(go())
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
        """A cheap value that changes when the root metadata is replaced (reader check); None
        if the store has no root metadata.

        Local: the file's inode, mtime and size. ``http(s)://`` and ``s3://``: the root
        ``zarr.json``'s strong validator from a metadata request (HEAD: its ETag, size and
        Last-Modified; no body), where the server gives one that must change with the bytes
        (:meth:`_validator_token`); otherwise, and for other backends, a hash of the whole
        ``zarr.json`` (a GET: ~64 KB for a 400-source mosaic, whose sources it lists). A
        transport failure is raised as the client raised it (the caller classifies it).
        """
        if self.is_local:
            try:
                st = os.stat(self._key_path("zarr.json"))
            except FileNotFoundError:
                return None
            return (st.st_ino, st.st_mtime_ns, st.st_size)
        if not self._no_validator:
            token = self._validator_token()
            if token is not _NO_VALIDATOR:
                return token
        data = self.get_bytes("zarr.json")
        return None if data is None else hashlib.blake2b(data, digest_size=16).digest()

    #: set once this location's server gave no strong validator (no ETag, a weak one, HEAD
    #: refused): later tokens GET and hash ``zarr.json`` without asking for one again
    _no_validator = False

    def _validator_token(self) -> object:
        """``("etag", ETag, size, Last-Modified, ...)`` of the root ``zarr.json`` from one
        metadata request (S3: with its version), None if it does not exist, or
        :data:`_NO_VALIDATOR` where this backend or server gives no validator that changes
        whenever the bytes do (then the caller hashes the bytes).

        ``s3://``: S3's ETag (an MD5 of the object, or of its parts, or a value unique to the
        upload where encrypted). ``http(s)://``: a strong ETag (not ``W/``), except nginx's,
        which is only the Last-Modified (whole seconds) and the size (:func:`_mtime_etag`: a
        store renamed into place can have both equal to the old one's), and except one whose
        Last-Modified is within :data:`FRESH_VALIDATOR_S` of the server's Date (an ETag made
        from the mtime in whole seconds, as lighttpd's, may not change on a rewrite of the same
        size within that second; asked again at the next check); a server without ETag
        (``python -m http.server`` sends only a Last-Modified in whole seconds) has none."""
        if not isinstance(self.target, str) or self.is_memory:
            return _NO_VALIDATOR
        if self.is_s3:
            fs, _ = self._fs()
            try:
                info = fs.info(self._key_path("zarr.json"), refresh=True)
            except FileNotFoundError:
                return None
            etag = info.get("ETag")
            if info.get("type") != "file" or not etag:
                self._no_validator = True
                return _NO_VALIDATOR
            return ("etag", etag, info.get("size"), str(info.get("LastModified")),
                    info.get("VersionId"))  # fmt: skip
        if not is_http(self.target):
            return _NO_VALIDATOR
        status, headers = self._http_head("zarr.json")
        if status in (404, 410):
            return None
        if status in (405, 501):  # HEAD not served: GET it
            self._no_validator = True
            return _NO_VALIDATOR
        etag, modified = headers.get("etag"), headers.get("last-modified")
        size = headers.get("content-length")
        if not etag or etag.startswith(("W/", "w/")) or _mtime_etag(etag, modified, size):
            self._no_validator = True
            return _NO_VALIDATOR
        if modified is not None and not _settled(modified, headers.get("date")):
            return _NO_VALIDATOR  # (for now: asked again at the next check)
        return ("etag", etag, size, modified)

    def _http_head(self, key: str) -> tuple[int, dict[str, str]]:
        """``(status, headers)`` (names lower-cased) of a HEAD of ``key`` through the store's
        fsspec HTTP session: its headers, authorisation and timeouts, redirects followed. A
        failed connection, or an error status other than "not found" (404, 410) and "HEAD not
        served" (405, 501), raises aiohttp's error, as a GET would."""
        from fsspec.asyn import sync

        fs, _ = self._fs()
        url = fs.encode_url(self._key_path(key))
        kwargs = dict(fs.kwargs)
        headers = {**(kwargs.pop("headers", None) or {}), "Accept-Encoding": "identity"}
        redirects = kwargs.pop("allow_redirects", True)

        async def go() -> tuple[int, dict[str, str]]:
            session = await fs.set_session()
            async with session.head(url, headers=headers, allow_redirects=redirects, **kwargs) as r:
                if r.status >= 400 and r.status not in (404, 405, 410, 501):
                    r.raise_for_status()
                return r.status, {k.lower(): v for k, v in r.headers.items()}

        return sync(fs.loop, go)


#: :meth:`LocationKeys._validator_token`'s "no strong validator here: hash the bytes"
_NO_VALIDATOR = object()
#: seconds a server's Last-Modified must lie before its Date for its ETag to be trusted as
#: changing on any rewrite (an ETag made of the mtime in whole seconds, nginx's, may not change
#: on a rewrite within that second; the margin covers a file system clock ahead of the server's)
FRESH_VALIDATOR_S = 60.0


def _mtime_etag(etag: str, modified: str | None, size: str | None) -> bool:
    """True for nginx's ETag, ``"<Last-Modified in hex seconds>-<size in hex>"``: no more
    than those two, which another file can share (written in the same second, same size)."""
    from email.utils import parsedate_to_datetime

    if modified is None or size is None:
        return False
    try:
        seconds = int(parsedate_to_datetime(modified).timestamp())
        return etag.strip('"') == f"{seconds:x}-{int(size):x}"
    except (TypeError, ValueError, IndexError, OverflowError):
        return False


def _settled(modified: str, date: str | None) -> bool:
    """True if the HTTP dates say ``modified`` (Last-Modified) lies at least
    :data:`FRESH_VALIDATOR_S` before ``date`` (the answer's Date; this machine's clock without
    one); False for a date that does not parse."""
    import time
    from email.utils import parsedate_to_datetime

    try:
        then = parsedate_to_datetime(modified).timestamp()
        now = parsedate_to_datetime(date).timestamp() if date else time.time()
    except (TypeError, ValueError, IndexError, OverflowError):
        return False
    return now - then >= FRESH_VALIDATOR_S


def link_if_absent(path: str, data: bytes) -> bool:
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
