"""Source rasters behind a URL (a COG on a web server or an object store, read through GDAL's
``/vsicurl/`` family): the HTTP settings GDAL reads them with, and what a failed open says
about the server.

GDAL's curl reads have no time limit by default, so a server that stopped answering held
``terrastream tile`` for ever, and a server answering HTTP 503 was reported as "not recognized
as being in a supported file format" (a usage error). :func:`remote_env` gives the opening of
a remote source the same rule as ``http(s)://`` stores (give up after
:data:`~tiler.transport.HTTP_TIMEOUT_S` without a byte) and a few retries of GDAL's transient
HTTP statuses; a variable the environment sets itself (``GDAL_HTTP_LOW_SPEED_TIME``...), or
the caller's ``rasterio.Env``, wins.
Everything GDAL does on a remote source runs inside it: the open, the header's side files
(``.msk``, ``.aux.xml``, asked for with the settings of the moment) and the reads.
:func:`server_failure` asks the server why an open failed.
"""

from __future__ import annotations

import ctypes
import functools
import http.client
import math
import os
import re
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

from tiler.transport import HTTP_TIMEOUT_S

#: GDAL config options for remote sources (each unless the environment sets it): give up on a
#: connection after ``HTTP_TIMEOUT_S``, or on a transfer slower than 1 byte/s for that long;
#: retry HTTP 429/502/503/504 twice, 1 s apart (GDAL's default delay is 30 s)
GDAL_HTTP_DEFAULTS: dict[str, str] = {
    "GDAL_HTTP_CONNECTTIMEOUT": f"{HTTP_TIMEOUT_S:g}",
    "GDAL_HTTP_LOW_SPEED_TIME": f"{HTTP_TIMEOUT_S:g}",
    "GDAL_HTTP_LOW_SPEED_LIMIT": "1",
    "GDAL_HTTP_MAX_RETRY": "2",
    "GDAL_HTTP_RETRY_DELAY": "1",
}
#: GDAL's network file systems (``/vsicurl/``, ``/vsis3/``... and the URLs rasterio maps to them)
_NETWORK_VSI = ("curl", "s3", "gs", "az", "adls", "oss", "swift", "webhdfs", "hdfs")
#: most seconds :func:`server_failure` waits for the server's answer (less if the environment
#: sets a shorter ``GDAL_HTTP_LOW_SPEED_TIME``)
PROBE_TIMEOUT_S = 10.0


def is_remote(path: str) -> bool:
    """True if GDAL reads ``path`` over the network (a URL or a network ``/vsi...`` path,
    possibly inside ``/vsizip/``...)."""
    return "://" in path or any(f"/vsi{fs}/" in path for fs in _NETWORK_VSI)


def gdal_http_options(
    environ: Mapping[str, str] | None = None, current: Mapping[str, object] | None = None
) -> dict[str, str]:
    """:data:`GDAL_HTTP_DEFAULTS` without the options ``environ`` (default ``os.environ``) or
    ``current`` (the caller's ``rasterio.Env`` options) sets."""
    env = os.environ if environ is None else environ
    cur = current or {}
    return {k: v for k, v in GDAL_HTTP_DEFAULTS.items() if k not in env and k not in cur}


def is_s3(path: str) -> bool:
    """True for a source GDAL reads from S3 (``s3://...``, ``/vsis3/...``)."""
    return str(path).startswith("s3://") or "/vsis3/" in str(path)


#: GDAL's own S3 endpoint settings: when one is set, GDAL is left to them
_GDAL_S3_KEYS = ("AWS_S3_ENDPOINT", "AWS_HTTPS", "AWS_VIRTUAL_HOSTING")


def gdal_s3_options(
    environ: Mapping[str, str] | None = None, current: Mapping[str, object] | None = None
) -> dict[str, str]:
    """GDAL's S3 endpoint settings from ``AWS_ENDPOINT_URL_S3`` or ``AWS_ENDPOINT_URL`` (what
    boto3, s3fs and obstore read, and terrastream's ``s3://`` stores honour), unless
    ``environ`` (default ``os.environ``) or ``current`` sets GDAL's own ``AWS_S3_ENDPOINT``:
    ``AWS_S3_ENDPOINT`` (host[:port]), ``AWS_HTTPS`` (NO for ``http://``) and
    ``AWS_VIRTUAL_HOSTING=FALSE`` (path-style addressing, as boto3 uses with an endpoint), each
    unless set. GDAL itself ignores ``AWS_ENDPOINT_URL``: an ``s3://`` source went to AWS."""
    env = os.environ if environ is None else environ
    cur = current or {}
    if "AWS_S3_ENDPOINT" in env or "AWS_S3_ENDPOINT" in cur:
        return {}
    endpoint = env.get("AWS_ENDPOINT_URL_S3") or env.get("AWS_ENDPOINT_URL")
    parts = urllib.parse.urlsplit(endpoint or "")
    if parts.scheme.lower() not in ("http", "https") or not parts.netloc:
        return {}
    out = {
        "AWS_S3_ENDPOINT": parts.netloc + parts.path.rstrip("/"),
        "AWS_HTTPS": "NO" if parts.scheme.lower() == "http" else "YES",
        "AWS_VIRTUAL_HOSTING": "FALSE",
    }
    return {k: v for k, v in out.items() if k not in env and k not in cur}


@contextmanager
def remote_env(*paths: str) -> Iterator[None]:
    """Inside, GDAL works with :func:`gdal_http_options` if one of ``paths`` is remote (its
    open, and the side files and reads that follow: GDAL asks for ``.msk``/``.aux.xml``
    files with the settings of the moment), and an S3 source with :func:`gdal_s3_options`
    (``AWS_ENDPOINT_URL``); the options of a ``rasterio.Env`` the caller entered win too."""
    if not any(is_remote(p) for p in paths):
        yield
        return
    import rasterio
    import rasterio.env

    current = rasterio.env.getenv() if rasterio.env.hasenv() else None
    opts = gdal_http_options(current=current)
    if any(is_s3(p) for p in paths):
        opts.update(gdal_s3_options(current=current))
    if not opts:
        yield
        return
    with rasterio.Env(**opts):
        yield


def http_url(path: str) -> str | None:
    """The ``http(s)://`` URL GDAL fetches for ``path`` (also behind ``/vsicurl/``), or None."""
    p = path.removeprefix("/vsicurl/")
    return p if p.startswith(("http://", "https://")) else None


def probe_timeout(environ: Mapping[str, str] | None = None) -> float:
    """Seconds :func:`server_failure` waits: :data:`PROBE_TIMEOUT_S`, or the environment's
    ``GDAL_HTTP_LOW_SPEED_TIME`` if that is shorter (a value that is not a number is ignored)."""
    env = os.environ if environ is None else environ
    try:
        own = float(env.get("GDAL_HTTP_LOW_SPEED_TIME", "nan"))
    except ValueError:
        own = math.nan
    return min(own, PROBE_TIMEOUT_S) if own > 0 else PROBE_TIMEOUT_S


def server_failure(url: str, timeout: float | None = None) -> tuple[str, int | None] | None:
    """Why the server at ``url`` cannot serve it: ``(what it did, HTTP status or None)``, or
    None if it serves the file's first byte (the failure was the file's, not the server's).
    One ranged ``GET`` of a byte, waiting ``timeout`` s (default :func:`probe_timeout`)."""
    timeout = probe_timeout() if timeout is None else timeout
    req = urllib.request.Request(url, headers={"Range": "bytes=0-0"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            r.read(1)
    except urllib.error.HTTPError as exc:
        return f"answers HTTP {exc.code} {exc.reason}", exc.code
    except TimeoutError:
        return f"did not answer in {timeout:g} s", None
    except urllib.error.URLError as exc:
        reason = exc.reason
        if isinstance(reason, TimeoutError):
            return f"did not answer in {timeout:g} s", None
        return f"cannot be reached ({reason})", None
    except (OSError, http.client.HTTPException) as exc:  # a dropped connection, a bad reply
        return f"failed ({type(exc).__name__}: {exc})", None
    return None


def slow_advice(what: str) -> str:
    """The advice to add for :func:`server_failure`'s ``what`` when the server did not answer in
    time ("" otherwise)."""
    if not what.startswith("did not answer"):
        return ""
    return " (GDAL_HTTP_LOW_SPEED_TIME sets the seconds a read may go without a byte)"


#: GDAL's words for a request refused for its credentials (S3's error codes, HTTP 401/403)
_GDAL_REFUSED = re.compile(
    r"HTTP (?:response|error) code:? *40[13]\b|Access ?Denied|InvalidAccessKeyId|"
    r"SignatureDoesNotMatch|ExpiredToken|InvalidToken",
    re.I,
)
#: GDAL's words for a server or network that failed (curl's errors, HTTP 429/5xx, timeouts)
_GDAL_FAILED = re.compile(
    r"CURL error|HTTP (?:response|error) code:? *(?:429|5\d\d)\b|timed? ?out|"
    r"Could not resolve|Failed to connect|Connection (?:refused|reset)|SlowDown|"
    r"ServiceUnavailable|InternalError",
    re.I,
)


def gdal_network_failure(message: str) -> str | None:
    """``"refused"`` or ``"failed"`` if GDAL's ``message`` about a network path says its
    server refused the credentials or failed (or the network did), else None."""
    if _GDAL_REFUSED.search(message):
        return "refused"
    if _GDAL_FAILED.search(message):
        return "failed"
    return None


@functools.cache
def _gdal_clear_cache() -> object | None:
    """GDAL's ``VSICurlClearCache`` from the libgdal rasterio's own extension module links
    (so never another GDAL's), or None when it cannot be found."""
    import rasterio._base

    try:
        fn = ctypes.CDLL(rasterio._base.__file__).VSICurlClearCache
    except (OSError, AttributeError):
        return None
    fn.restype, fn.argtypes = None, []
    return fn


def forget_failed_open() -> bool:
    """Make GDAL ask the server again after a remote open failed: its network file systems
    remember a path they could not reach as absent for the rest of the process, so a second
    open said "does not exist in the file system" whatever the server did (a usage error
    instead of the network named). The whole network cache is cleared: its per-path clearing
    (``VSICurlPartialClearCache``, tried with the path, its folder and ``/vsis3/``) leaves that
    memory in place; a failed open is rare, and other sources' next reads only fetch again.
    False when GDAL's function cannot be found."""
    fn = _gdal_clear_cache()
    if fn is None:
        return False
    fn()  # type: ignore[operator]
    return True
