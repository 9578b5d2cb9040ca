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


class ServerProcess:
    """``with ServerProcess(directory) as srv:`` a :class:`LoopbackServer` (faults on every key)
    in a child process, for clients that hold the GIL while they wait for an answer (GDAL, in
    some of its calls: an in-process server could not answer them). ``srv.url``;
    ``srv.send(cmd)``: ``stall`` (answer nothing), ``release`` (the stalled requests end
    unanswered), ``status N`` / ``status -`` (answer every request with HTTP N / normally)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = str(directory)
        self.url = ""

    def __enter__(self) -> ServerProcess:
        import subprocess
        import sys

        self._proc = subprocess.Popen(
            [sys.executable, __file__, self.directory],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.url = self._proc.stdout.readline().strip()
        if not self.url.startswith("http://"):
            self._proc.kill()
            raise RuntimeError(f"the test server did not start: {self.url!r}")
        return self

    def send(self, cmd: str) -> None:
        """Apply ``cmd`` in the server (returns once it has)."""
        self._proc.stdin.write(cmd + "\n")
        self._proc.stdin.flush()
        if self._proc.stdout.readline().strip() != "ok":
            raise RuntimeError(f"the test server did not take {cmd!r}")

    def __exit__(self, *exc) -> None:
        self._proc.stdin.close()  # the server ends at the end of its input
        try:
            self._proc.wait(timeout=10)
        except Exception:  # noqa: BLE001 (a server that does not end is killed)
            self._proc.kill()
            self._proc.wait(timeout=10)
        self._proc.stdout.close()


def _serve(directory: str) -> None:
    """The child of :class:`ServerProcess`: serve ``directory``, take commands from stdin."""
    import sys

    srv = LoopbackServer(directory)
    srv.handler.fail_scope = "all"
    with srv as url:
        print(url, flush=True)
        for line in sys.stdin:
            cmd, _, arg = line.strip().partition(" ")
            if cmd == "stall":
                srv.release.clear()
                srv.stall.set()
            elif cmd == "release":
                srv.release.set()
            elif cmd == "status":
                srv.handler.fail_status = None if arg == "-" else int(arg)
            else:
                print(f"unknown command {line!r}", flush=True)
                continue
            print("ok", flush=True)


if __name__ == "__main__":
    import sys

    _serve(sys.argv[1])
