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

import difflib
import functools
import inspect
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
    if no_credentials(exc):  # (fixed outside the store, like a refused access)
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


def no_credentials(exc: BaseException) -> bool:
    """True if ``exc`` is botocore's "no (or partial) S3 credentials were found"."""
    boto = sys.modules.get("botocore.exceptions")
    return boto is not None and isinstance(
        exc, boto.NoCredentialsError | boto.PartialCredentialsError
    )


#: what to do when no S3 credentials were found
CREDENTIALS_ADVICE = (
    "no S3 credentials were found: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY (or "
    'AWS_PROFILE), give them as --storage-options \'{"key": "...", "secret": "..."}\', '
    "or read a public bucket without them with --storage-options '{\"anon\": true}'"
)


def missing_bucket(exc: BaseException) -> bool:
    """True if ``exc`` is s3fs's "The specified bucket does not exist" (a ``FileNotFoundError``
    naming no bucket)."""
    return isinstance(exc, FileNotFoundError) and "bucket does not exist" in str(exc).lower()


def bucket_of(url: str) -> str:
    """The bucket of an object-store URL (``s3://bucket/key`` → ``bucket``)."""
    return str(url).split("://", 1)[-1].split("/", 1)[0]


def missing_bucket_message(url: str) -> str:
    """The message for writing or reading ``url`` in a bucket that does not exist."""
    bucket = bucket_of(url)
    return (
        f"the bucket {bucket!r} of {url!r} does not exist: create it (e.g. `aws s3 mb "
        f"s3://{bucket}`) or check the bucket's name and the endpoint (AWS_ENDPOINT_URL or "
        "the storage option 'endpoint_url')"
    )


def advice(exc: BaseException) -> str:
    """What to do about the transport error ``exc``."""
    if no_credentials(exc):
        return CREDENTIALS_ADVICE
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
    ``client_kwargs`` sets its own ``timeout`` (a number there is taken as these seconds).
    aiohttp's default (300 s in total, per request) let a server that stopped answering hang
    a flight for five minutes. An option fsspec's HTTP filesystem does not take is refused
    (:func:`check_option_names`).
    """
    so = dict(options or {})
    check_option_names(so, "http")
    seconds = _seconds(so.pop(TIMEOUT_OPTION, HTTP_TIMEOUT_S))
    client = dict(so.get("client_kwargs") or {})
    import aiohttp

    if "timeout" in client and not isinstance(client["timeout"], aiohttp.ClientTimeout):
        # aiohttp refuses a number here ("use timeout=ClientTimeout(...)"): taken as the
        # ``timeout`` option's seconds, for a JSON option cannot hold a ClientTimeout
        seconds = _seconds(client.pop("timeout"), "client_kwargs.timeout")
    if "timeout" not in client:
        client["timeout"] = aiohttp.ClientTimeout(
            total=None, sock_connect=float(seconds), sock_read=float(seconds)
        )
    so["client_kwargs"] = client
    return so


def _seconds(value: Any, name: str = TIMEOUT_OPTION) -> float:
    """``value`` as a number of seconds > 0, or :class:`StorageOptionsError` naming ``name``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not (math.isfinite(value) and value > 0)
    ):
        raise StorageOptionsError(
            f"storage option {name!r} must be a number of seconds > 0, got "
            f'{value!r}; e.g. {{"{TIMEOUT_OPTION}": 30}}'
        )
    return float(value)


def http_timeout(options: dict[str, Any] | None) -> float:
    """The seconds an ``http(s)://`` store's reads wait (:func:`http_options`'s): the
    ``timeout`` option, else a number in ``client_kwargs.timeout``, else
    :data:`HTTP_TIMEOUT_S`."""
    so = dict(options or {})
    if TIMEOUT_OPTION in so:
        return _seconds(so[TIMEOUT_OPTION])
    client = so.get("client_kwargs") or {}
    if isinstance(client, dict) and isinstance(client.get("timeout"), int | float):
        return _seconds(client["timeout"], "client_kwargs.timeout")
    return HTTP_TIMEOUT_S


#: options fsspec's filesystems take themselves (its instance and listings caches)
_FSSPEC_OWN = ("skip_instance_cache", "use_listings_cache", "listings_expiry_time", "max_paths")
#: the storage options most given, named first when an unknown one is refused
_COMMON = {
    "http": ("timeout", "headers", "client_kwargs", "auth"),
    "s3": ("endpoint_url", "key", "secret", "token", "anon", "timeout", "client_kwargs",
           "config_kwargs", "profile"),
}  # fmt: skip


def _names(func: Any, skip: tuple[str, ...] = ("self",), *, whole: bool = True) -> set[str]:
    """The keyword parameters of ``func`` (not ``*args``/``**kwargs``, nor ``skip``). With
    ``whole``, a ``func`` taking ``**kwargs`` raises ``TypeError``: its names are not all
    known (a later library version), so that level is not checked rather than refused."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    params = inspect.signature(func).parameters.values()
    if whole and any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        raise TypeError(f"{func!r} takes **kwargs")
    return {p.name for p in params if p.kind in kinds and p.name not in skip}


def _level(names: Any) -> frozenset[str]:
    """``names()`` as a frozenset, or an empty one (not checked) if they are not all known."""
    try:
        return frozenset(names())
    except (TypeError, ValueError):
        return frozenset()


@functools.lru_cache(maxsize=4)
def option_names(kind: str) -> dict[str, frozenset[str]]:
    """The storage options a ``kind`` (``http`` or ``s3``) store's filesystem takes: ``""`` the
    top level, ``client_kwargs`` and ``config_kwargs`` those dicts' keys (empty: not checked).
    Read from the client libraries' signatures (what they would otherwise refuse with a bare
    ``TypeError`` when the first request is made)."""
    if kind == "http":
        import aiohttp
        from fsspec.implementations.http import HTTPFileSystem

        def top() -> set[str]:
            # fsspec's own, then each request's keywords (headers, auth, proxy, ssl...)
            own = _names(HTTPFileSystem.__init__, whole=False) | set(_FSSPEC_OWN)
            request = _names(aiohttp.ClientSession._request, ("self", "method", "str_or_url"))
            return own | request | {TIMEOUT_OPTION}

        return {"": _level(top), "client_kwargs": _level(lambda: _names(aiohttp.ClientSession))}
    if kind == "s3":
        import botocore.config
        import botocore.session
        import s3fs
        from aiobotocore.config import AioConfig
        from aiobotocore.session import AioSession

        def top() -> set[str]:
            # s3fs gives what it does not know to aiobotocore's session
            own = _names(s3fs.S3FileSystem.__init__, whole=False) | _names(AioSession.__init__)
            return own | set(_FSSPEC_OWN) | {TIMEOUT_OPTION}

        def config() -> set[str]:  # (AioConfig gives the rest to botocore's Config)
            return set(botocore.config.Config.OPTION_DEFAULTS) | _names(
                AioConfig.__init__, whole=False
            )

        create = botocore.session.Session.create_client
        return {
            "": _level(top),
            "client_kwargs": _level(lambda: _names(create, ("self", "service_name"))),
            "config_kwargs": _level(config),
        }
    return {}


def check_option_names(options: dict[str, Any] | None, kind: str) -> None:
    """Refuse a storage option the ``kind`` store's filesystem does not take (a typo such as
    ``endpoint_ur``) with :class:`StorageOptionsError` naming it and the closest known one,
    instead of the client library's ``TypeError`` at the first request."""
    so = dict(options or {})
    if not so:
        return
    try:
        known = option_names(kind)
    except ImportError:  # (the library is missing: its filesystem fails alike, later)
        return
    for where, names in known.items():
        given = so if not where else so.get(where)
        if not isinstance(given, dict) or not names:
            if where and given is not None and not isinstance(given, dict):
                raise StorageOptionsError(
                    f"storage option {where!r} must be a JSON object (key: value), got {given!r}"
                )
            continue
        for key in given:
            if key in names:
                continue
            name = f"{where}.{key}" if where else key
            close = difflib.get_close_matches(str(key), sorted(names), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}? " if close else ""
            common = ", ".join(n for n in _COMMON.get(kind, ()) if n in names) if not where else ""
            scheme = "http(s)://" if kind == "http" else f"{kind}://"
            listed = f"; the usual ones are {common}" if common else ""
            raise StorageOptionsError(
                f"unknown storage option {name!r} for an {scheme} store: {hint}check its "
                f"spelling{listed} (see README, storage options)"
            )


def s3fs_options(options: dict[str, Any] | None, *, write: bool = False) -> dict[str, Any]:
    """fsspec options for an ``s3://`` store: botocore's retries :data:`S3FS_RETRIES`
    (:data:`S3FS_WRITE_RETRIES` with ``write``) unless ``config_kwargs`` sets ``retries`` or
    the environment sets ``AWS_MAX_ATTEMPTS`` or ``AWS_RETRY_MODE``; the ``timeout`` option
    (seconds) becomes botocore's connect and read timeouts. An option s3fs does not take is
    refused (:func:`check_option_names`)."""
    so = dict(options or {})
    check_option_names(so, "s3")
    config = dict(so.get("config_kwargs") or {})
    if TIMEOUT_OPTION in so:
        # the same rule as an http(s) store's: botocore's connect and read timeouts (unless
        # ``config_kwargs`` sets them); s3fs itself has no ``timeout``
        seconds = _seconds(so.pop(TIMEOUT_OPTION))
        config.setdefault("connect_timeout", seconds)
        config.setdefault("read_timeout", seconds)
        so["config_kwargs"] = config
    if os.environ.get("AWS_MAX_ATTEMPTS") or os.environ.get("AWS_RETRY_MODE"):
        return so
    if "retries" not in config:
        config["retries"] = dict(S3FS_WRITE_RETRIES if write else S3FS_RETRIES)
        so["config_kwargs"] = config
    return so
