"""The read path of an ``s3://`` store: zarr's ``ObjectStore`` over obstore (a Rust HTTP
client, faster than s3fs for many small ranged reads) where obstore is installed and every
storage option has an obstore equivalent; otherwise :class:`tiler.location.Location` reads
through fsspec (s3fs). ``TERRASTREAM_S3_READER=fsspec`` forces s3fs."""

from __future__ import annotations

import os
from datetime import timedelta
from typing import Any

from zarr.abc.store import Store

#: ``obstore`` (default where installed) or ``fsspec``: the zarr store used to read s3:// stores
S3_READER_ENV = "TERRASTREAM_S3_READER"
#: obstore's retries of a failed read (``retry_config``): 2 retries 0.1–0.2 s apart, at most
#: 10 s in all. Its default (10 retries, backoff to 15 s, 180 s in all) spent 1.4–20 s and 11
#: connections on one read from a server that drops them (2–7 s on a refused one) before the
#: session's own retries (``retries``, ``backoff_s``) could count one failure.
S3_READ_RETRY: dict[str, Any] = {
    "max_retries": 2,
    "backoff": {"init_backoff": timedelta(seconds=0.1), "max_backoff": timedelta(seconds=1),
                "base": 2},
    "retry_timeout": timedelta(seconds=10),
}  # fmt: skip
_OBSTORE_KEYS = {
    "key": "access_key_id",
    "secret": "secret_access_key",
    "token": "session_token",
    "endpoint_url": "endpoint",
}


def open_s3_reader(url: str, storage_options: dict[str, Any] | None = None) -> Store | None:
    """A read-only zarr ``ObjectStore`` (obstore, Rust HTTP client) for an ``s3://`` URL, or None
    if obstore is missing or an option has no obstore equivalent (then fsspec reads it).

    Credentials, region and endpoint also come from the environment (``AWS_*``), like s3fs.
    """
    if not url.startswith("s3://"):
        return None
    try:
        from obstore.store import S3Store
        from zarr.storage import ObjectStore
    except ImportError:
        return None
    so = dict(storage_options or {})
    client = dict(so.pop("client_kwargs", None) or {})
    config: dict[str, Any] = {}
    if "region_name" in client:
        config["region"] = client.pop("region_name")
    if "endpoint_url" in client:
        so.setdefault("endpoint_url", client.pop("endpoint_url"))
    if client:
        return None
    if so.pop("anon", False):
        config["skip_signature"] = True
    for k in list(so):
        if k in _OBSTORE_KEYS:
            config[_OBSTORE_KEYS[k]] = so.pop(k)
    if so:
        return None  # e.g. profile, requester_pays: only s3fs knows them
    endpoint = (
        config.get("endpoint")
        or os.environ.get("AWS_ENDPOINT_URL_S3")
        or (os.environ.get("AWS_ENDPOINT_URL"))
    )
    if endpoint and str(endpoint).startswith("http://"):
        config["endpoint"] = endpoint
        client_options = {"allow_http": True}
    else:
        client_options = {}
    bucket, _, prefix = url[len("s3://") :].partition("/")
    store = S3Store(bucket, prefix=prefix.strip("/") or None, client_options=client_options,
                    retry_config=S3_READ_RETRY, **config)  # fmt: skip
    return ObjectStore(store, read_only=True)
