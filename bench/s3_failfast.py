"""How long an ``s3://`` store takes to report a dead server, and how many connections it tries.

Two loopback endpoints: one that refuses connections (a closed port) and one that accepts each
connection, reads the request and closes it without an answer. Against each, ``open_store``
through s3fs and through obstore (its first contact goes through s3fs either way), and one read
of a key through each reader (what a session's loader does per block attempt), each with
terrastream's client retries (``tiler.transport.S3FS_RETRIES`` and ``S3FS_TRIES``,
``tiler.s3_reader.S3_READ_RETRY``) and with the clients' defaults (botocore's legacy retries,
s3fs's 5 tries, obstore's default retry config), in this process. Prints a table and writes
``bench/results/s3_failfast.json``.

Usage: python bench/s3_failfast.py [--out FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.common import RESULTS, machine_info, portable  # noqa: E402


class Dropping:
    """A loopback server that closes every connection unanswered (``count``: connections)."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(64)
        self.sock.settimeout(0.1)
        self.count = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="bench-dropping-s3", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.sock.getsockname()[1]}"

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            self.count += 1
            conn.settimeout(5)
            with contextlib.suppress(OSError):
                conn.recv(65536)
            conn.close()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=10)
        self.sock.close()


def _refused_url() -> str:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    return f"http://127.0.0.1:{port}"


@contextlib.contextmanager
def _clients(defaults: bool):
    """The options of a Location in this run: with ``defaults``, the clients' own retries
    (which S3FS_RETRIES, S3FS_TRIES and S3_READ_RETRY replace)."""
    import s3fs

    import tiler.s3_reader as s3r
    import tiler.transport as tr

    s3fs.S3FileSystem.clear_instance_cache()
    saved = s3r.S3_READ_RETRY, getattr(tr, "S3FS_TRIES", None)
    so: dict = {}
    if defaults:
        so["config_kwargs"] = {"retries": {"mode": "legacy"}}
        s3r.S3_READ_RETRY = None
        tr.S3FS_TRIES = s3fs.S3FileSystem.retries  # (code without S3FS_TRIES ignores it)
    try:
        yield so
    finally:
        s3r.S3_READ_RETRY, tr.S3FS_TRIES = saved


def _open(url: str, reader: str, defaults: bool) -> str:
    from tiler.location import Location
    from tiler.store import open_store

    os.environ["TERRASTREAM_S3_READER"] = reader
    with _clients(defaults) as so:
        try:
            open_store(Location("s3://b/x.zarr", {"endpoint_url": url, **so}))
        except Exception as exc:  # noqa: BLE001 - the failure is the measurement
            return type(exc).__name__
    return "opened"


def _read_fsspec(url: str, defaults: bool) -> str:
    """One read of a key through the store a Location gives zarr for ``s3://`` (s3fs)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.storage import FsspecStore

    from tiler.location import Location

    with _clients(defaults) as so:
        loc = Location("s3://b/x.zarr", {"endpoint_url": url, **so})
        try:
            if hasattr(loc, "zarr_args"):
                store = loc.zarr_args("r")[0]
            else:  # the code before Location.zarr_args (an A/B run): what zarr made of it
                store = FsspecStore.from_url(loc.target, loc.fsspec_options(), read_only=True)
            asyncio.run(store.get("zarr.json", default_buffer_prototype()))
        except Exception as exc:  # noqa: BLE001
            return type(exc).__name__
    return "read"


def _read(url: str, defaults: bool) -> str:
    from zarr.core.buffer import default_buffer_prototype

    import tiler.s3_reader as s3r

    saved = s3r.S3_READ_RETRY
    s3r.S3_READ_RETRY = None if defaults else saved  # None: obstore's default
    try:
        store = s3r.open_s3_reader("s3://b/x.zarr", {"endpoint_url": url})
        asyncio.run(store.get("zarr.json", default_buffer_prototype()))
    except Exception as exc:  # noqa: BLE001
        return type(exc).__name__
    finally:
        s3r.S3_READ_RETRY = saved
    return "read"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=RESULTS / "s3_failfast.json")
    a = ap.parse_args(argv)
    for k in ("AWS_ENDPOINT_URL", "AWS_SESSION_TOKEN", "AWS_MAX_ATTEMPTS", "AWS_RETRY_MODE"):
        os.environ.pop(k, None)
    os.environ.update(AWS_DEFAULT_REGION="us-east-1", AWS_ACCESS_KEY_ID="bench",
                      AWS_SECRET_ACCESS_KEY="bench")  # fmt: skip
    rows = []
    print(f"{'server':9} {'what':22} {'retries':9} {'result':24} {'conns':>5} {'s':>7}")
    for server in ("refuses", "drops"):
        for what in (
            "open_store (s3fs)",
            "open_store (obstore)",
            "one read (s3fs)",
            "one read (obstore)",
        ):
            for defaults in (True, False):
                drop = Dropping() if server == "drops" else None
                url = drop.url if drop else _refused_url()
                t0 = time.perf_counter()
                if what.startswith("open_store"):
                    result = _open(url, "obstore" if "obstore" in what else "fsspec", defaults)
                elif what == "one read (s3fs)":
                    result = _read_fsspec(url, defaults)
                else:
                    result = _read(url, defaults)
                seconds = time.perf_counter() - t0
                conns = drop.count if drop else None
                if drop:
                    drop.close()
                row = {"server": server, "what": what,
                       "retries": "client default" if defaults else "terrastream",
                       "result": result, "connections": conns, "seconds": seconds}  # fmt: skip
                rows.append(row)
                print(
                    f"{server:9} {what:22} {'client' if defaults else 'ours':9} {result:24} "
                    f"{'' if conns is None else conns:>5} {seconds:7.2f}"
                )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(portable({"rows": rows, "machine": machine_info()}), indent=1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
