"""Remote stores over HTTP: a server without (suffix) range support gets a clear error."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
import requests
from demtools import fractal, write_dem
from rangeserver import LoopbackServer, RangeHandler
from typer.testing import CliRunner

from cli.main import app
from tiler.errors import RemoteStoreError, StoreError
from tiler.location import Location
from tiler.remote import _check_cached, check_range_support
from tiler.store import TerrainStore, open_store
from tiler.tile import TileOptions, tile


class QuietPlain(SimpleHTTPRequestHandler):
    """What ``python -m http.server`` runs: ignores Range, sends whole files with 200."""

    def log_message(self, *args) -> None:
        pass


class NoSuffixRanges(RangeHandler):
    """Serves ``bytes=a-b`` but answers suffix ranges ``bytes=-N`` with 400 (like some CDNs)."""

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if re.match(r"bytes=-\d+$", self.headers.get("Range", "") or ""):
            self.send_error(400, "suffix ranges not supported")
            return
        super().do_GET()


class NeedsToken(RangeHandler):
    """A store behind header authorisation: 401 without ``Authorization: Bearer secret``."""

    stall, release = threading.Event(), threading.Event()  # (never stalls)

    def _refused(self) -> bool:
        if self.headers.get("Authorization") == "Bearer secret":
            return False
        self.send_error(401, "no token")
        return True

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if not self._refused():
            super().do_GET()

    def do_HEAD(self) -> None:  # noqa: N802 (http.server API)
        if not self._refused():
            super().do_HEAD()


class Slow(RangeHandler):
    """Answers the root metadata after 1 s."""

    stall, release = threading.Event(), threading.Event()  # (never stalls)

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if self.path.endswith("/zarr.json") and self.path.count("/") == 2:
            time.sleep(1.0)
        super().do_GET()


@contextmanager
def serve(directory, handler):
    server = ThreadingHTTPServer(("127.0.0.1", 0), partial(handler, directory=str(directory)))
    server.daemon_threads = True
    t = threading.Thread(target=server.serve_forever, name="test-http-plain", daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        t.join(timeout=5)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    d = tmp_path_factory.mktemp("remote")
    src = write_dem(d / "dem.tif", fractal((80, 80), seed=13))
    tile(src, d / "s.zarr", TileOptions(block_size=33))
    return d


@pytest.fixture(autouse=True)
def _fresh_cache():
    _check_cached.cache_clear()
    yield
    _check_cached.cache_clear()


def test_plain_http_server_is_named_as_the_cause(served):
    with serve(served, QuietPlain) as url:
        with pytest.raises(RemoteStoreError, match="does not support HTTP range requests") as e:
            open_store(f"{url}/s.zarr")
        assert "python -m http.server" in str(e.value)
        assert isinstance(e.value, StoreError) and isinstance(e.value, ConnectionError)
        # positive control: without the check, the same server gives the far-away symptom
        # users met (a complaint about a block's data), not the cause: through zarr a
        # checksum; read directly, the sizes the server answered, blamed on it (since session
        # 41: more bytes than a range asked for cannot come from the store)
        s = TerrainStore(f"{url}/s.zarr")
        with pytest.raises(StoreError, match=r"answered \d+ bytes for the \d+-byte index"):
            s.read_block((0, 0))
        s = TerrainStore(f"{url}/s.zarr", direct_reads=False)
        with pytest.raises(StoreError, match="checksum"):
            s.read_block((0, 0))


def test_server_without_suffix_ranges(served):
    with (
        serve(served, NoSuffixRanges) as url,
        pytest.raises(RemoteStoreError, match=r"not suffix ranges \(`bytes=-N`\)"),
    ):
        open_store(f"{url}/s.zarr")


def test_range_server_opens_and_reads(served):
    local = open_store(served / "s.zarr")
    with LoopbackServer(served) as url:
        s = open_store(f"{url}/s.zarr")
        np.testing.assert_array_equal(s.read_block((1, 1)), local.read_block((1, 1)))
        with pytest.raises(StoreError, match="was not found"):
            check_range_support(f"{url}/missing.zarr")


def test_ctrl_c_during_a_remote_blocks_level_reads_is_raised_after_its_pool(served, monkeypatch):
    """A remote block's levels are read on a pool (tiler.store): a Ctrl-C that comes while the
    main thread waits for them is raised by tiler.interrupt once the pool has stopped, not
    inside the pool's bookkeeping (where it could leave a lock held and hang the shutdown)."""
    import os
    import signal

    with LoopbackServer(served) as url:
        s = TerrainStore(f"{url}/s.zarr", direct_reads=False)
        assert s.k > 0 and not s.direct_reads  # the pool path (zarr's reads)
        read = s._read

        def read_then_ctrl_c(name, block, level, *args):
            if level == 0:  # in a pool thread, while the main thread waits on the futures
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.1)
            return read(name, block, level, *args)

        monkeypatch.setattr(s, "_read", read_then_ctrl_c)
        with pytest.raises(KeyboardInterrupt) as e:
            s.read_block((1, 1))
    assert e.traceback[-1].path.name == "interrupt.py"  # raised by the check, after the pool
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert not [t for t in threading.enumerate() if t.name.startswith("terrastream-read")]


def test_the_probe_sends_the_stores_headers_and_keeps_its_timeout(served):
    """The range probe asks as the store's reads do: with the storage options' headers (a
    store behind a token opened, before, never: the probe's 401), and within their timeout
    (it had its own 10 s)."""
    so = {"client_kwargs": {"headers": {"Authorization": "Bearer secret"}}}
    local = open_store(served / "s.zarr")
    with serve(served, NeedsToken) as url:
        with pytest.raises(RemoteStoreError, match="HTTP 401 .* access was refused"):
            open_store(f"{url}/s.zarr")  # (the control: no token)
        s = open_store(Location(f"{url}/s.zarr", so))
        np.testing.assert_array_equal(s.read_block((1, 1)), local.read_block((1, 1)))
    with serve(served, Slow) as url:
        with pytest.raises(RemoteStoreError, match=r"did not answer within 0.5 s.*'timeout'"):
            open_store(Location(f"{url}/s.zarr", {"timeout": 0.5}))
        open_store(Location(f"{url}/s.zarr", {"timeout": 5}))


class RangesButNotForLevel(RangeHandler):
    """Serves ranges, except on the shards of ``levels/0`` (whole objects: a proxy rule)."""

    stall, release = threading.Event(), threading.Event()  # (never stalls)

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if "/levels/0/c/" in self.path:
            del self.headers["Range"]
        super().do_GET()


def test_a_server_ignoring_ranges_on_some_keys_is_blamed_not_the_store(served):
    """The probe of the root metadata passes; a level's shard is then answered whole: the
    error names the server (before: 'the store is damaged: verify it', and verify said ok)."""
    with serve(served, RangesButNotForLevel) as url:
        s = open_store(f"{url}/s.zarr")
        with pytest.raises(StoreError, match="ignored the byte range") as e:
            s.read_block((0, 0))
        assert "not the store" in str(e.value) and "verify" not in str(e.value)


def test_non_http_urls_are_not_probed():
    check_range_support("memory://x")  # nothing to ask: no error, no request
    check_range_support("some/local/store.zarr")  # a local path


def test_cli_info_exits_non_zero_with_the_cause(served):
    with serve(served, QuietPlain) as url:
        r = CliRunner().invoke(app, ["info", f"{url}/s.zarr"])
    assert r.exit_code != 0
    assert "does not support HTTP range requests" in r.output
    assert "checksum" not in r.output


def test_real_python_m_http_server(served):
    """The very server users try: ``python -m http.server`` in a subprocess."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
        cwd=served,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 20
        while True:
            try:
                requests.get(url, timeout=1)
                break
            except requests.ConnectionError:
                if time.monotonic() > deadline:
                    pytest.fail("python -m http.server did not start within 20 s")
                time.sleep(0.1)
        with pytest.raises(RemoteStoreError, match="does not support HTTP range requests"):
            open_store(f"{url}/s.zarr")
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_info_over_http_says_the_sizes_are_unknown_not_zero(served):
    """An http(s) server lists no files: info's sizes are unknown (null), not 0 B and a ratio
    of 0.000 as before; the same store on disk gives them (the control)."""
    import json

    from tiler.info import store_info

    local = store_info(served / "s.zarr")
    assert local["bytes"]["total"] > 0 and local["ratio_to_raw"] > 0
    with LoopbackServer(served) as url:
        d = store_info(f"{url}/s.zarr")
        assert d["bytes"] is None and d["ratio_to_raw"] is None
        assert all(r["bytes"] is None for r in d["bytes_per_level"])
        out = CliRunner().invoke(app, ["info", f"{url}/s.zarr"]).output
        assert "stored bytes unknown" in out and "0 B" not in out
        js = json.loads(CliRunner().invoke(app, ["info", f"{url}/s.zarr", "--json"]).output)
        assert js["bytes"] is None
