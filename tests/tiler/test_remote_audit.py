"""Remote (HTTP/S3) reads, the audit's defects: each broken server or option (the positive
control, which the code before these fixes got wrong) beside the normal case.

1. a transient 503 on an existence check is the server's failure, not a missing chunk;
2. a server answering ``bytes=-1`` with the first byte is named, not blamed on the store;
3. the range probe's urllib3 errors (a stalled body, a short one) name the store;
4. an unknown storage option is a usage error naming it (and the likely one);
5. S3 without credentials, or into a missing bucket, names the store and what to do;
6. an http(s) store URL with a query string is refused up front (a remote source keeps it);
7. an ``s3://`` source honours ``AWS_ENDPOINT_URL``, and a dead endpoint is the server's.

HTTP servers run on 127.0.0.1 in this process (or a child, for GDAL); moto's S3 server runs in
a child process (GDAL holds the GIL in some calls). All are stopped by the tests.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
import threading
import time
from contextlib import contextmanager
from functools import partial
from http.server import ThreadingHTTPServer

import pytest
import rasterio.errors
from demtools import fractal, write_dem
from rangeserver import LoopbackServer, RangeHandler, ServerProcess
from typer.testing import CliRunner

from cli.main import app
from tiler import source_http, transport
from tiler.errors import (
    BucketNotFoundError,
    RemoteStoreError,
    SourceError,
    SourceUnavailableError,
    StorageOptionsError,
    StoreUnavailableError,
    StoreURLError,
)
from tiler.location import Location
from tiler.remote import _check_cached, check_range_support
from tiler.source_header import open_raster
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

runner = CliRunner()
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


def cli(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A folder holding ``dem.tif`` and its store ``s.zarr`` (3×3 blocks, checksummed)."""
    d = tmp_path_factory.mktemp("audit")
    src = write_dem(d / "dem.tif", fractal((80, 80), seed=7))
    tile(src, d / "s.zarr", TileOptions(block_size=33, workers=1))
    return d


@pytest.fixture(autouse=True)
def _fresh_probe_cache():
    _check_cached.cache_clear()
    yield
    _check_cached.cache_clear()


@contextmanager
def serve(directory, handler):
    """``handler`` (a :class:`RangeHandler` subclass) serving ``directory`` on 127.0.0.1."""
    release = threading.Event()
    h = type("H", (handler,), {"stall": threading.Event(), "release": release})
    server = ThreadingHTTPServer(("127.0.0.1", 0), partial(h, directory=str(directory)))
    server.daemon_threads = True
    t = threading.Thread(target=server.serve_forever, name="test-audit-http", daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        release.set()
        server.shutdown()
        server.server_close()
        t.join(timeout=5)


# ---- 1. an existence check answered 503 ---------------------------------------------------
class Flaky(RangeHandler):
    """Every 2nd GET of a path holding ``match`` answers 503 (a server failing now and then),
    or every one with ``always``."""

    match = "index/exists/c/"
    always = False
    seen: dict[str, int]

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if self.match in self.path:
            with RangeHandler._lock:
                n = self.seen[self.path] = self.seen.get(self.path, 0) + 1
            if self.always or n % 2 == 0:
                self.send_error(503)
                return
        super().do_GET()


def flaky(always: bool = False) -> type:
    return type("F", (Flaky,), {"seen": {}, "always": always})


def test_an_existence_check_answered_503_is_unavailable_not_missing(served):
    with serve(served, flaky(always=True)) as url:
        loc = Location(f"{url}/s.zarr")
        with pytest.raises(StoreUnavailableError, match="not the store") as e:
            loc.key_exists("index/exists/c/0/0")  # (fsspec's exists said False: "missing")
        assert "index/exists/c/0/0" in str(e.value) and url in str(e.value)
        # the normal case: a key there is there, a 404 is absent
        assert loc.key_exists("zarr.json") is True
        assert loc.key_exists("index/zmin/c/9/9") is False
        assert loc.exists() in (True, False)  # (a directory URL: whatever the server says)


def test_verify_and_open_over_a_flaky_server_conclude_nothing(served):
    with serve(served, flaky()) as url, pytest.raises(StoreUnavailableError, match="not the"):
        verify_store(f"{url}/s.zarr")  # (said "chunk ... is missing", 9 bad blocks)
    with serve(served, flaky()) as url:
        r = cli("verify", f"{url}/s.zarr")
        assert r.exit_code == 1 and "not the store" in r.output, r.output
        assert "bad block" not in r.output and "--repair" not in r.output
    with serve(served, type("Z", (Flaky,), {"seen": {}, "match": "index/zmax/c/"})) as url:
        r = cli("info", f"{url}/s.zarr")
        assert r.exit_code == 1 and "not the store" in r.output, r.output
        assert "damaged" not in r.output
    with LoopbackServer(served) as url:  # the normal case: a good server, a good store
        assert verify_store(f"{url}/s.zarr").ok
        assert cli("info", f"{url}/s.zarr").exit_code == 0


# ---- 2. a suffix range answered with the first byte ---------------------------------------
class FirstBytesForSuffix(RangeHandler):
    """A naive range implementation: ``bytes=-N`` answered with the first N bytes (206,
    ``Content-Range: bytes 0-(N-1)/size``)."""

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        m = re.match(r"bytes=-(\d+)$", self.headers.get("Range", "") or "")
        if m:
            self.headers.replace_header("Range", f"bytes=0-{int(m.group(1)) - 1}")
        super().do_GET()


class WrongFirstByte(RangeHandler):
    """``bytes=0-0`` answered with byte 1 (``Content-Range: bytes 1-1/size``)."""

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        if (self.headers.get("Range") or "") == "bytes=0-0":
            self.headers.replace_header("Range", "bytes=1-1")
        super().do_GET()


def test_a_server_answering_suffix_ranges_with_the_first_bytes_is_named(served):
    with serve(served, FirstBytesForSuffix) as url:
        with pytest.raises(RemoteStoreError, match=r"not suffix ranges \(`bytes=-N`\)") as e:
            open_store(f"{url}/s.zarr")  # (export: "checksum do not match ... damaged")
        assert "Content-Range 'bytes 0-0/" in str(e.value) and "not the last byte" in str(e.value)
        r = cli("export", f"{url}/s.zarr", served / "out.tif", "--overwrite")
        assert r.exit_code == 1 and "suffix ranges" in r.output, r.output
        assert "do not match" not in r.output and "damaged" not in r.output
    with (
        serve(served, WrongFirstByte) as url,
        pytest.raises(RemoteStoreError, match="answers byte ranges wrongly"),
    ):
        check_range_support(f"{url}/s.zarr")
    with LoopbackServer(served) as url:  # the normal case
        check_range_support(f"{url}/s.zarr")
        assert open_store(f"{url}/s.zarr").read_block((0, 0)).size


# ---- 3. the probe's own urllib3 errors -----------------------------------------------------
class StalledBody(RangeHandler):
    """Sends the headers of a 1-byte answer, then nothing until released."""

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        self.send_response(206)
        self.send_header("Content-Length", "1")
        self.send_header("Content-Range", "bytes 0-0/10")
        self.end_headers()
        self.wfile.flush()
        self.release.wait(timeout=30)
        self.close_connection = True


class ShortBody(RangeHandler):
    """Promises a 1-byte body and closes the connection without it."""

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        self.send_response(206)
        self.send_header("Content-Length", "1")
        self.send_header("Content-Range", "bytes 0-0/10")
        self.end_headers()
        self.close_connection = True


def test_the_probe_names_the_store_for_a_stalled_or_short_body(served):
    with serve(served, StalledBody) as url:
        t = time.monotonic()
        with pytest.raises(RemoteStoreError, match=r"did not answer within 0.5 s.*'timeout'"):
            check_range_support(f"{url}/s.zarr", {"timeout": 0.5})  # (ReadTimeoutError)
        assert time.monotonic() - t < 5
        r = cli("info", f"{url}/s.zarr", "--storage-options", '{"timeout": 0.5}')
        assert r.exit_code == 1 and "did not answer within" in r.output, r.output
        assert "ReadTimeoutError" not in r.output
    with (
        serve(served, ShortBody) as url,
        pytest.raises(RemoteStoreError, match=r"cannot reach .*zarr\.json.*the server runs"),
    ):
        check_range_support(f"{url}/s.zarr")  # (ProtocolError)
    with LoopbackServer(served) as url:  # the normal case, with the same option
        check_range_support(f"{url}/s.zarr", {"timeout": 0.5})


# ---- 4. unknown storage options ------------------------------------------------------------
@pytest.mark.parametrize(
    ("url", "options", "named", "suggested"),
    [
        ("s3://b/s.zarr", {"endpoint_ur": "http://127.0.0.1:9"}, "endpoint_ur", "endpoint_url"),
        ("s3://b/s.zarr", {"client_kwargs": {"region_nam": "x"}}, "client_kwargs.region_nam",
         "region_name"),
        ("s3://b/s.zarr", {"config_kwargs": {"retires": {}}}, "config_kwargs.retires", "retries"),
        ("http://127.0.0.1:9/s.zarr", {"timeot": 5}, "timeot", "timeout"),
        ("http://127.0.0.1:9/s.zarr", {"header": {"A": "b"}}, "header", "headers"),
        ("http://127.0.0.1:9/s.zarr", {"client_kwargs": {"header": {}}}, "client_kwargs.header",
         "headers"),
    ],
)  # fmt: skip
def test_an_unknown_storage_option_is_refused_naming_it(url, options, named, suggested):
    with pytest.raises(StorageOptionsError) as e:  # (a TypeError at the first request)
        Location(url, options)
    msg = str(e.value)
    assert f"unknown storage option {named!r}" in msg and f"did you mean {suggested!r}" in msg
    r = cli("info", url, "--storage-options", json.dumps(options))
    assert r.exit_code == 2 and named in r.output and "TypeError" not in r.output, r.output


def test_the_documented_storage_options_are_taken():
    """The normal case: README's options, and the usual s3fs/fsspec ones, pass; ``timeout``
    on an s3:// store becomes botocore's timeouts (s3fs has none: a TypeError before)."""
    Location("s3://b/s.zarr", {"endpoint_url": "http://127.0.0.1:9", "key": "k", "secret": "s",
                               "anon": False, "client_kwargs": {"region_name": "us-east-1"},
                               "config_kwargs": {"retries": {"max_attempts": 1}}})  # fmt: skip
    so = Location("s3://b/s.zarr", {"timeout": 5}).fsspec_options()
    assert "timeout" not in so
    assert so["config_kwargs"]["connect_timeout"] == so["config_kwargs"]["read_timeout"] == 5
    own = {"timeout": 5, "config_kwargs": {"read_timeout": 60}}
    assert Location("s3://b/s.zarr", own).fsspec_options()["config_kwargs"]["read_timeout"] == 60
    Location("http://127.0.0.1:9/s.zarr", {"timeout": 5, "headers": {"A": "b"},
                                          "client_kwargs": {"headers": {"A": "b"}}})  # fmt: skip
    with pytest.raises(StorageOptionsError, match="'timeout' must be a number"):
        Location("s3://b/s.zarr", {"timeout": "5"})


def test_a_number_in_client_kwargs_timeout_is_taken_as_seconds(served):
    """aiohttp refused ``client_kwargs.timeout`` as a number (a ValueError at the first read);
    it is now the same seconds as the ``timeout`` option, for the reads and the probe."""
    import aiohttp

    so = transport.http_options({"client_kwargs": {"timeout": 7}})
    t = so["client_kwargs"]["timeout"]
    assert isinstance(t, aiohttp.ClientTimeout) and t.sock_read == t.sock_connect == 7
    with pytest.raises(StorageOptionsError, match="'client_kwargs.timeout' must be a number"):
        transport.http_options({"client_kwargs": {"timeout": -1}})
    with LoopbackServer(served) as url:
        so = {"timeout": 5, "client_kwargs": {"timeout": 5}}
        assert open_store(Location(f"{url}/s.zarr", so)).read_block((0, 0)).size
        r = cli("info", f"{url}/s.zarr", "--storage-options", json.dumps(so))
        assert r.exit_code == 0, r.output


# ---- 6. a store URL with a query string ---------------------------------------------------
def test_a_store_url_with_a_query_string_is_refused_up_front(served):
    with LoopbackServer(served) as url:
        with pytest.raises(StoreURLError, match="query string.*header") as e:
            Location(f"{url}/s.zarr?sig=1")  # (probed as ".../s.zarr?sig=1/zarr.json": 403)
        assert isinstance(e.value, ValueError)
        with pytest.raises(StoreURLError, match="fragment"):
            Location(f"{url}/s.zarr#x")
        r = cli("info", f"{url}/s.zarr?sig=1")
        assert r.exit_code == 2 and "query string" in r.output and '"headers"' in r.output
        assert "credentials" not in r.output
        # the normal case: the same store without it; and headers are the way to a token
        assert cli("info", f"{url}/s.zarr").exit_code == 0
        so = '{"headers": {"Authorization": "Bearer x"}}'
        assert cli("info", f"{url}/s.zarr", "--storage-options", so).exit_code == 0


def test_a_remote_source_keeps_its_query_string(served, tmp_path):
    """Sources are GDAL's URLs: a signed URL (``?sig=...``) of a source still tiles."""
    with ServerProcess(served) as srv:
        with open_raster(f"{srv.url}/dem.tif?sig=1") as ds:
            assert ds.width == 80
        r = cli("tile", f"{srv.url}/dem.tif?sig=1", tmp_path / "q.zarr", "--block-size", "33")
        assert r.exit_code == 0, r.output


# ---- 5 and 7. S3: credentials, buckets, sources --------------------------------------------
MOTO = textwrap.dedent(
    """
    import logging, sys
    from moto.server import ThreadedMotoServer
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    s = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    s.start()
    print("http://%s:%d" % s.get_host_and_port(), flush=True)
    sys.stdin.read()
    s.stop()
    """
)
S3_ENV = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE",
          "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_DEFAULT_REGION", "AWS_REGION",
          "AWS_S3_ENDPOINT", "AWS_HTTPS", "AWS_VIRTUAL_HOSTING", "AWS_MAX_ATTEMPTS",
          "AWS_RETRY_MODE")  # fmt: skip


@pytest.fixture(scope="module")
def moto_url():
    """``http://127.0.0.1:<port>`` of moto's S3 server in a child process (for the module)."""
    pytest.importorskip("moto.server")
    proc = subprocess.Popen([sys.executable, "-c", MOTO], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        url = proc.stdout.readline().strip()
        if not url.startswith("http://"):
            pytest.fail(f"moto did not start: {url!r}")
        yield url
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        proc.stdout.close()


@pytest.fixture
def s3env(moto_url, monkeypatch, tmp_path):
    """The environment pointing at moto with credentials; a fresh HOME (no ~/.aws)."""
    import s3fs

    for k in S3_ENV:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    monkeypatch.setenv("AWS_ENDPOINT_URL", moto_url)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    s3fs.S3FileSystem.clear_instance_cache()
    yield moto_url
    s3fs.S3FileSystem.clear_instance_cache()


_N = [0]


def _bucket() -> str:
    import s3fs

    _N[0] += 1
    name = f"audit-{_N[0]}-{int(time.time() * 1000) % 10**8}"
    s3fs.S3FileSystem().mkdir(name)
    return name


def test_no_s3_credentials_names_the_store_and_what_to_do(s3env, served, monkeypatch):
    import s3fs

    b = _bucket()
    url = f"s3://{b}/s.zarr"
    tile(served / "dem.tif", url, TileOptions(block_size=33, workers=1))
    assert cli("info", url).exit_code == 0  # the normal case: with credentials
    monkeypatch.delenv("AWS_ACCESS_KEY_ID")
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    s3fs.S3FileSystem.clear_instance_cache()
    r = cli("info", url)  # (was "NoCredentialsError: Unable to locate credentials")
    assert r.exit_code == 1, r.output
    for words in (url, "AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", '"key"', '"anon": true'):
        assert words in r.output, r.output
    assert "traceback" not in r.output
    from botocore.exceptions import NoCredentialsError

    assert transport.is_transport_error(NoCredentialsError())
    assert "AWS_ACCESS_KEY_ID" in transport.advice(NoCredentialsError())
    assert "AWS_ACCESS_KEY_ID" not in transport.advice(ConnectionError("x"))


def test_a_missing_bucket_is_named(s3env, served, tmp_path):
    url = "s3://no-such-bucket-audit/s.zarr"
    with pytest.raises(BucketNotFoundError, match="'no-such-bucket-audit'.*create it"):
        Location(url).put_bytes("x", b"1")
    r = cli("tile", served / "dem.tif", url, "--block-size", "33", "--workers", "1")
    assert r.exit_code == 2, r.output  # (was "FileNotFoundError: The specified bucket ...")
    assert "bucket 'no-such-bucket-audit'" in r.output and "create it" in r.output, r.output
    b = _bucket()  # the normal case: a bucket there
    Location(f"s3://{b}/s.zarr").put_bytes("x", b"1")
    assert Location(f"s3://{b}/s.zarr").get_bytes("x") == b"1"


def test_gdal_s3_options_come_from_aws_endpoint_url():
    env = {"AWS_ENDPOINT_URL": "http://127.0.0.1:9000"}
    assert source_http.gdal_s3_options(env) == {
        "AWS_S3_ENDPOINT": "127.0.0.1:9000", "AWS_HTTPS": "NO", "AWS_VIRTUAL_HOSTING": "FALSE"
    }  # fmt: skip
    env = {"AWS_ENDPOINT_URL": "http://a:1", "AWS_ENDPOINT_URL_S3": "https://s3.example.org/"}
    assert source_http.gdal_s3_options(env)["AWS_S3_ENDPOINT"] == "s3.example.org"
    assert source_http.gdal_s3_options(env)["AWS_HTTPS"] == "YES"
    # GDAL's own settings win, each one
    assert source_http.gdal_s3_options({**env, "AWS_S3_ENDPOINT": "h:1"}) == {}
    assert "AWS_HTTPS" not in source_http.gdal_s3_options({**env, "AWS_HTTPS": "NO"})
    assert source_http.gdal_s3_options(env, {"AWS_S3_ENDPOINT": "h:1"}) == {}
    assert source_http.gdal_s3_options({}) == {}


def test_an_s3_source_honours_aws_endpoint_url(s3env, served, tmp_path, monkeypatch):
    import s3fs

    b = _bucket()
    s3fs.S3FileSystem().put(str(served / "dem.tif"), f"{b}/dem.tif")
    src = f"s3://{b}/dem.tif"
    with open_raster(src) as ds:  # (GDAL went to <bucket>.s3.us-east-1.amazonaws.com)
        assert ds.width == 80
    r = cli("tile", src, tmp_path / "s.zarr", "--block-size", "33", "--workers", "1")
    assert r.exit_code == 0, r.output
    # the control: without the mapping GDAL asks AWS (no network here: it fails)
    monkeypatch.setattr(source_http, "gdal_s3_options", lambda *a, **k: {})
    monkeypatch.setenv("GDAL_HTTP_MAX_RETRY", "0")
    with pytest.raises((SourceError, SourceUnavailableError)):
        open_raster(src)


def test_a_dead_s3_endpoint_of_a_source_is_the_servers_failure(s3env, served, monkeypatch):
    monkeypatch.setenv("AWS_S3_ENDPOINT", "127.0.0.1:1")  # GDAL's own: nothing listens
    monkeypatch.setenv("AWS_HTTPS", "NO")
    monkeypatch.setenv("AWS_VIRTUAL_HOSTING", "FALSE")
    monkeypatch.setenv("GDAL_HTTP_MAX_RETRY", "0")
    with pytest.raises(SourceUnavailableError, match="not the file.*endpoint") as e:
        open_raster("s3://bucket1/dem.tif")  # (was SourceError: a usage error, exit 2)
    assert "127.0.0.1:1" in str(e.value)
    # (another key: GDAL remembers a path it failed to stat as absent, for the process)
    r = cli("tile", "s3://bucket2/dem.tif", served / "x.zarr", "--block-size", "33")
    assert r.exit_code == 1 and "not the file" in r.output, r.output


@pytest.mark.parametrize(
    ("said", "unavailable"),
    [
        ("CURL error: Could not resolve host: b.s3.amazonaws.com", True),
        ("HTTP response code: 503", True),
        ("HTTP response code: 403", True),
        ("'/vsis3/b/x.tif' not recognized as being in a supported file format.", False),
        ("'/vsis3/b/x.tif' does not exist in the file system", False),
    ],
)
def test_gdal_network_failures_of_s3_sources_are_told_apart(monkeypatch, said, unavailable):
    """The control: GDAL's words about the file itself stay a SourceError (exit 2)."""
    import tiler.source_header as sh

    def fail(path):
        raise rasterio.errors.RasterioIOError(said)

    monkeypatch.setattr(sh.rasterio, "open", fail)
    with pytest.raises((SourceError, SourceUnavailableError)) as e:
        open_raster("s3://b/x.tif")
    assert isinstance(e.value, SourceUnavailableError) == unavailable, str(e.value)
    assert "s3://b/x.tif" in str(e.value)
