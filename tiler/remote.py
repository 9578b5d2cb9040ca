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

from tiler.errors import RemoteStoreError, StoreError

TIMEOUT_S = 10.0
_CONTENT_RANGE = re.compile(r"bytes (\d+)-(\d+)/(\d+|\*)")


def is_http(url: str) -> bool:
    """True for ``http://`` and ``https://`` URLs."""
    return str(url).lower().startswith(("http://", "https://"))


def _probe(url: str, rng: str, timeout: float) -> tuple[int, str | None, int]:
    """``(status, Content-Range, body length)`` of a GET with ``Range: rng``."""
    import requests

    try:
        with requests.get(url, headers={"Range": rng}, timeout=timeout, stream=True) as r:
            body = r.raw.read(1 << 16, decode_content=True) if r.status_code < 400 else b""
            return r.status_code, r.headers.get("Content-Range"), len(body)
    except requests.RequestException as exc:
        raise RemoteStoreError(f"cannot reach {url!r}: {exc}") from exc


def check_range_support(store_url: str, timeout: float = TIMEOUT_S) -> None:
    """Raise ``RemoteStoreError`` unless the server of an HTTP store answers byte-range and
    suffix-range requests with ``206 Partial Content``; a no-op for other URLs."""
    if not is_http(store_url):
        return
    _check_cached(str(store_url).rstrip("/"), float(timeout))


@functools.lru_cache(maxsize=64)
def _check_cached(base: str, timeout: float) -> None:
    url = f"{base}/zarr.json"
    status, crange, n = _probe(url, "bytes=0-0", timeout)
    if status == 404:
        raise StoreError(f"no terrastream store at {base!r}: {url} was not found (HTTP 404)")
    if status >= 400:
        raise RemoteStoreError(f"the server of {base!r} answered HTTP {status} for {url}")
    if status != 206 or not crange or not _CONTENT_RANGE.match(crange) or n != 1:
        raise RemoteStoreError(
            f"the server of {base!r} does not support HTTP range requests: asked for byte 0 of "
            f"{url} it answered {status} with {n} bytes and no valid Content-Range (a plain "
            "`python -m http.server` does this). A store is read in byte ranges; serve it with "
            "a server that supports them (nginx, Apache, caddy, any object store), or copy it "
            "to a local directory."
        )
    status, crange, n = _probe(url, "bytes=-1", timeout)
    if status != 206 or not crange or not _CONTENT_RANGE.match(crange) or n != 1:
        raise RemoteStoreError(
            f"the server of {base!r} supports byte ranges but not suffix ranges (`bytes=-N`): "
            f"asked for the last byte of {url} it answered {status}. Sharded levels are read "
            "with suffix ranges (each shard's index is at its end); serve the store with a "
            "server that supports them, or copy it to a local directory."
        )
