"""A loopback HTTP file server with Range support and optional latency, for store tests."""

from __future__ import annotations

import os
import re
import threading
import time
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

_RANGE = re.compile(r"bytes=(\d*)-(\d*)$")


class RangeHandler(SimpleHTTPRequestHandler):
    """Serves files with single byte-range support (what object stores offer)."""

    latency_s = 0.0
    requests = 0
    _lock = threading.Lock()
    #: faults for block data (the chunks of ``levels/``, ``errors/``, ``mask/``), per server:
    #: answer with this HTTP status, or (``stall`` set) answer nothing until ``release`` is set
    fail_status: int | None = None
    fail_match: str | None = None  # only chunks whose path holds this (None: every chunk)
    fail_scope = "blocks"  # "all": every key, the store's metadata and index too
    stall: threading.Event
    release: threading.Event

    def _faulty(self) -> bool:
        """Apply the server's fault to a block-data request; True if it was answered so."""
        block_chunk = "/c/" in self.path and any(  # not an array's metadata
            f"/{a}/" in self.path for a in ("levels", "errors", "mask")
        )
        if self.fail_scope != "all" and not block_chunk:
            return False
        if self.fail_match is not None and self.fail_match not in self.path:
            return False
        if self.stall.is_set():
            self.release.wait(timeout=600)  # a server that stopped answering (SIGSTOP)
            self.close_connection = True
            return True
        if self.fail_status is not None:
            self.send_error(self.fail_status)
            return True
        return False

    def log_message(self, *args) -> None:  # keep test output clean
        pass

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        with RangeHandler._lock:
            RangeHandler.requests += 1
        if self.latency_s:
            time.sleep(self.latency_s)
        if self._faulty():
            return
        path = self.translate_path(self.path)
        if not os.path.isfile(path):
            self.send_error(404)
            return
        size = os.path.getsize(path)
        m = _RANGE.match(self.headers.get("Range", "") or "")
        start, end = 0, size - 1
        if m:
            a, b = m.groups()
            if a == "":
                start = max(0, size - int(b))
            else:
                start = int(a)
                end = min(size - 1, int(b)) if b else size - 1
            if start >= size:
                self.send_error(416)
                return
        with open(path, "rb") as f:
            f.seek(start)
            body = f.read(end - start + 1)
        self.send_response(206 if m else 200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Accept-Ranges", "bytes")
        if m:
            self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.end_headers()
        self.wfile.write(body)

    def do_HEAD(self) -> None:  # noqa: N802
        path = self.translate_path(self.path)
        if not os.path.isfile(path):
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(os.path.getsize(path)))
        self.send_header("Accept-Ranges", "bytes")
        self.end_headers()


class _Server(ThreadingHTTPServer):
    request_queue_size = 64  # opening a store fetches ~20 keys at once (default backlog: 5)


class LoopbackServer:
    """``with LoopbackServer(directory, latency_s) as url:`` serves a folder on 127.0.0.1."""

    def __init__(self, directory: str | os.PathLike, latency_s: float = 0.0) -> None:
        self.stall, self.release = threading.Event(), threading.Event()
        handler = type(
            "H",
            (RangeHandler,),
            {"latency_s": latency_s, "stall": self.stall, "release": self.release},
        )
        self.handler = handler  # set ``handler.fail_status`` to answer block data with it
        self._server = _Server(("127.0.0.1", 0), partial(handler, directory=str(directory)))
        self._server.daemon_threads = True
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="test-http-server", daemon=True
        )

    def __enter__(self) -> str:
        self._thread.start()
        return f"http://127.0.0.1:{self._server.server_address[1]}"

    def __exit__(self, *exc) -> None:
        self.release.set()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)
