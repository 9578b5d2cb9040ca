"""Remote stores over plain HTTP: check the server serves byte ranges before reading.

A store's chunks are read with ``Range: bytes=a-b`` requests and sharded levels also with
suffix ranges (``bytes=-N``, the shard index at the end of each shard). A server without them
(``python -m http.server`` ignores ``Range`` and sends the whole file) makes every read wrong,
which surfaces far away as a checksum mismatch. :func:`check_range_support` asks for one byte
of the root ``zarr.json`` both ways and raises :class:`~tiler.errors.RemoteStoreError` naming
the missing capability.
"""

from __future__ import annotations

import functools
import re
from typing import Any

from tiler.errors import RemoteStoreError, StoreError
from tiler.transport import HTTP_TIMEOUT_S, TIMEOUT_OPTION, http_options, http_timeout

#: the probe's timeout when the storage options set none: the store's own default
TIMEOUT_S = HTTP_TIMEOUT_S
_CONTENT_RANGE = re.compile(r"bytes (\d+)-(\d+)/(\d+|\*)")


def is_http(url: str) -> bool:
    """True for ``http://`` and ``https://`` URLs."""
    return str(url).lower().startswith(("http://", "https://"))


def _probe(
    url: str, rng: str, timeout: float, headers: tuple[tuple[str, str], ...] = ()
) -> tuple[int, str | None, int]:
    """``(status, Content-Range, body length)`` of a GET with ``Range: rng`` (and ``headers``,
    the store's own: authorisation, ...)."""
    import requests
    import urllib3.exceptions

    try:
        asked = {**dict(headers), "Range": rng}
        with requests.get(url, headers=asked, timeout=timeout, stream=True) as r:
            body = r.raw.read(1 << 16, decode_content=True) if r.status_code < 400 else b""
            return r.status_code, r.headers.get("Content-Range"), len(body)
    except (requests.Timeout, urllib3.exceptions.ReadTimeoutError) as exc:
        # (a body that stalls after the headers times out in urllib3's read, not in requests)
        raise RemoteStoreError(
            f"{url!r} did not answer within {timeout:g} s: check the server, or raise the "
            f"storage option {TIMEOUT_OPTION!r} (seconds)"
        ) from exc
    except (requests.RequestException, urllib3.exceptions.HTTPError) as exc:
        # (urllib3's ProtocolError: a connection closed before the promised Content-Length)
        raise RemoteStoreError(
            f"cannot reach {url!r} ({type(exc).__name__}): check the URL, that the server runs "
            "and the network"
        ) from exc


def probe_settings(options: dict[str, Any] | None) -> tuple[float, tuple[tuple[str, str], ...]]:
    """The probe's ``(timeout, headers)`` from a store's storage options: the ``timeout``
    option (or a number in ``client_kwargs.timeout``; default :data:`TIMEOUT_S`) and the
    headers fsspec's HTTP reads send (``headers`` and ``client_kwargs.headers``), so a store
    behind header authorisation opens."""
    so = dict(options or {})
    http_options(so)  # validates the options (StorageOptionsError naming a bad one)
    seconds = http_timeout(so)
    headers: dict[str, str] = {}
    for h in ((so.get("client_kwargs") or {}).get("headers"), so.get("headers")):
        if isinstance(h, dict):
            headers.update({str(k): str(v) for k, v in h.items()})
    return float(seconds), tuple(sorted(headers.items()))


def check_range_support(store_url: str, options: dict[str, Any] | None = None) -> None:
    """Raise ``RemoteStoreError`` unless the server of an HTTP store answers byte-range and
    suffix-range requests with ``206 Partial Content``, asked with the store's storage
    ``options`` (:func:`probe_settings`); a no-op for other URLs."""
    if not is_http(store_url):
        return
    _check_cached(str(store_url).rstrip("/"), *probe_settings(options))


@functools.lru_cache(maxsize=64)
def _check_cached(base: str, timeout: float, headers: tuple[tuple[str, str], ...] = ()) -> None:
    url = f"{base}/zarr.json"
    status, crange, n = _probe(url, "bytes=0-0", timeout, headers)
    if status == 404:
        raise StoreError(f"no terrastream store at {base!r}: {url} was not found (HTTP 404)")
    if status in (401, 403):
        raise RemoteStoreError(
            f"the server of {base!r} answered HTTP {status} for {url}: access was refused, not "
            "the store damaged: check the credentials (the storage options' headers) and try "
            "again"
        )
    if status >= 400:
        raise RemoteStoreError(f"the server of {base!r} answered HTTP {status} for {url}")
    if status != 206 or _byte_range(crange) is None or n != 1:
        raise RemoteStoreError(
            f"the server of {base!r} does not support HTTP range requests: asked for byte 0 of "
            f"{url} it answered {status} with {n} bytes and no valid Content-Range (a plain "
            "`python -m http.server` does this). A store is read in byte ranges; serve it with "
            "a server that supports them (nginx, Apache, caddy, any object store), or copy it "
            "to a local directory."
        )
    first = _byte_range(crange)
    if first is not None and first[:2] != (0, 0):
        raise RemoteStoreError(
            f"the server of {base!r} answers byte ranges wrongly: asked for byte 0 of {url} "
            f"(Range: bytes=0-0) it answered Content-Range {crange!r}. A store is read in byte "
            "ranges; serve it with a server that answers them as asked (nginx, Apache, caddy, "
            "any object store), or copy it to a local directory."
        )
    status, crange, n = _probe(url, "bytes=-1", timeout, headers)
    if status != 206 or _byte_range(crange) is None or n != 1:
        raise RemoteStoreError(
            f"the server of {base!r} supports byte ranges but not suffix ranges (`bytes=-N`): "
            f"asked for the last byte of {url} it answered {status}. Sharded levels are read "
            "with suffix ranges (each shard's index is at its end); serve the store with a "
            "server that supports them, or copy it to a local directory."
        )
    start, end, total = _byte_range(crange)  # type: ignore[misc]
    if total is None or not start == end == total - 1:
        raise RemoteStoreError(
            f"the server of {base!r} supports byte ranges but not suffix ranges (`bytes=-N`): "
            f"asked for the last byte of {url} (Range: bytes=-1) it answered Content-Range "
            f"{crange!r}, not the last byte: its suffix ranges are broken (a naive range "
            "implementation reads `bytes=-N` as the first N bytes). Sharded levels are read with "
            "suffix ranges (each shard's index is at its end), so every read would fail its "
            "checksum; serve the store with a server that supports them (nginx, Apache, caddy, "
            "any object store), or copy it to a local directory."
        )


def _byte_range(crange: str | None) -> tuple[int, int, int | None] | None:
    """``(first, last, total or None)`` of a ``Content-Range: bytes a-b/n`` header (None: none,
    or not that form, or a range that ends before it starts)."""
    m = _CONTENT_RANGE.fullmatch(crange.strip()) if crange else None
    if m is None:
        return None
    start, end = int(m.group(1)), int(m.group(2))
    total = None if m.group(3) == "*" else int(m.group(3))
    if end < start or (total is not None and end >= total):
        return None
    return start, end, total
