"""Telling a failed connection from a damaged store, and how long a remote read may hang.

A read of a remote store can fail because the server or the network did (a timeout, a refused
or dropped connection, an HTTP 503), because access was refused (HTTP 401/403, a
``PermissionError``), or because the store is damaged (a checksum that does not match, a chunk
that is missing). The first two are fixed outside the store and say nothing about it; the last
is worth ``terrastream verify``. :func:`is_transport_error` tells them apart for the clients
terrastream reads through: aiohttp (fsspec's ``http(s)://``), obstore (``s3://``), botocore
(s3fs) and the built-in ``TimeoutError``/``ConnectionError``/``PermissionError``.

Pure: no I/O; the client libraries are only looked up if they are already imported.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tiler.errors import StorageOptionsError, StoreUnavailableError

#: default seconds an ``http(s)://`` read may go without a byte (connect, then each read)
HTTP_TIMEOUT_S = 30.0
#: the storage option (``http(s)://`` only) that sets it, in seconds
TIMEOUT_OPTION = "timeout"
#: botocore's retries for ``s3://`` through s3fs (``config_kwargs``) unless the storage options
#: or ``AWS_MAX_ATTEMPTS``/``AWS_RETRY_MODE`` set them: 2 attempts per request. botocore's
#: default (legacy, 5 attempts) under s3fs's own 5 made a server that drops connections cost
#: 25 connections per request (an ``open_store``: 50 connections, 34–47 s; now 20, 4–5 s) and a
#: refused one 5–10 s. Standard mode retries the same transient errors (throttling, 5xx,
#: dropped connections); s3fs still retries dropped connections and throttling 5 times over
#: ~2 s; sessions retry failed reads themselves.
S3FS_RETRIES: dict[str, Any] = {"mode": "standard", "total_max_attempts": 2}
#: the same for a store being written (``tile``'s destination, its workers'): botocore's 5
#: attempts, in standard mode. A tiling run has no retries of its own around a chunk write
#: (a failure stops it, to be rerun), so a transient 500 there is worth 4 more tries.
S3FS_WRITE_RETRIES: dict[str, Any] = {"mode": "standard", "total_max_attempts": 5}
#: s3fs's own tries of a request (its ``retries``, a class attribute, not a storage option)
#: around botocore's attempts, for a store being read: 2. s3fs's 5 tries sleep 1.9 s in all
#: between them, so a server that dropped connections cost an ``open_store`` 20 connections and
#: 4–5 s even with :data:`S3FS_RETRIES`; sessions retry a failed block read themselves.
S3FS_TRIES = 2
#: the same for a store being written: s3fs's own default, 5 (see :data:`S3FS_WRITE_RETRIES`).
S3FS_WRITE_TRIES = 5


def is_transport_error(exc: BaseException) -> bool:
    """True if ``exc`` is the server's or the network's failure (or a refused access), not the
    store's content."""
    if isinstance(exc, TimeoutError | ConnectionError | PermissionError):
        return True  # s3fs turns a 403 into PermissionError
    aiohttp = sys.modules.get("aiohttp")
    if aiohttp is not None and isinstance(exc, aiohttp.ClientError):
        return True  # ClientResponseError (5xx, 403...), payload, disconnect, connector errors
    boto = sys.modules.get("botocore.exceptions")  # s3fs lets some through untranslated
    if boto is not None and isinstance(exc, boto.ConnectionError | boto.HTTPClientError):
        return True
    obstore_exc = sys.modules.get("obstore.exceptions")
    if obstore_exc is not None and isinstance(exc, obstore_exc.BaseError):
        # NotFoundError is a missing key, which zarr's ObjectStore turns into an absent chunk
        return not isinstance(exc, obstore_exc.NotFoundError)
    return False


def describe(exc: BaseException, most: int = 400) -> str:
    """``exc``'s first line with its type (a bare ``TimeoutError()`` has no message; obstore's
    go on with a multi-line debug dump), at most ``most`` characters."""
    text = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), "")
    if len(text) > most:
        text = text[: most - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def advice(exc: BaseException) -> str:
    """What to do about the transport error ``exc``."""
    if isinstance(exc, PermissionError) or getattr(exc, "status", None) in (401, 403):
        return (
            "access was refused, not the store damaged: check the credentials (storage "
            "options, AWS_* variables) or the files' permissions, and try again"
        )
    if isinstance(exc, TimeoutError):
        return (
            "the server did not answer in time: check it and the connection, or raise the "
            f"storage option {TIMEOUT_OPTION!r} (seconds; http(s) stores), and try again"
        )
    return "the server or the network failed, not the store: check them and try again"


def unavailable(subject: str, url: str, exc: BaseException, **where: Any) -> StoreUnavailableError:
    """The error for a transport failure ``exc`` fetching ``subject`` from ``url`` (``where``:
    ``array``/``block``/``level``), worded with what to do."""
    return StoreUnavailableError(
        f"cannot fetch {subject} from {url!r}: {describe(exc)}; {advice(exc)}", **where
    )


@contextmanager
def server_errors(subject: str, url: str) -> Iterator[None]:
    """Inside, a transport failure becomes :func:`unavailable`'s error; others pass as they
    are."""
    try:
        yield
    except Exception as exc:
        if isinstance(exc, StoreUnavailableError) or not is_transport_error(exc):
            raise
        raise unavailable(subject, url, exc) from exc


def http_options(options: dict[str, Any] | None) -> dict[str, Any]:
    """fsspec options for an ``http(s)://`` store: ``timeout`` (seconds without a byte, default
    :data:`HTTP_TIMEOUT_S`) becomes aiohttp's connect and read timeouts, unless
    ``client_kwargs`` sets its own ``timeout``. aiohttp's default (300 s in total, per
    request) let a server that stopped answering hang a flight for five minutes.
    """
    so = dict(options or {})
    seconds = so.pop(TIMEOUT_OPTION, HTTP_TIMEOUT_S)
    if (
        isinstance(seconds, bool)
        or not isinstance(seconds, int | float)
        or not (math.isfinite(seconds) and seconds > 0)
    ):
        raise StorageOptionsError(
            f"storage option {TIMEOUT_OPTION!r} must be a number of seconds > 0, got "
            f'{seconds!r}; e.g. {{"{TIMEOUT_OPTION}": 30}}'
        )
    client = dict(so.get("client_kwargs") or {})
    if "timeout" not in client:
        import aiohttp

        client["timeout"] = aiohttp.ClientTimeout(
            total=None, sock_connect=float(seconds), sock_read=float(seconds)
        )
    so["client_kwargs"] = client
    return so


def s3fs_options(options: dict[str, Any] | None, *, write: bool = False) -> dict[str, Any]:
    """fsspec options for an ``s3://`` store: botocore's retries :data:`S3FS_RETRIES`
    (:data:`S3FS_WRITE_RETRIES` with ``write``) unless ``config_kwargs`` sets ``retries`` or
    the environment sets ``AWS_MAX_ATTEMPTS`` or ``AWS_RETRY_MODE``."""
    so = dict(options or {})
    if os.environ.get("AWS_MAX_ATTEMPTS") or os.environ.get("AWS_RETRY_MODE"):
        return so
    config = dict(so.get("config_kwargs") or {})
    if "retries" not in config:
        config["retries"] = dict(S3FS_WRITE_RETRIES if write else S3FS_RETRIES)
        so["config_kwargs"] = config
    return so
