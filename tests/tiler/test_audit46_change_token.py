"""A remote reader's change check (``TerrainStore.check_unchanged``, at most once a second)
asks for the root ``zarr.json``'s strong validator (HTTP HEAD: ETag; S3: head_object's ETag),
not its bytes: a mosaic's ``zarr.json`` lists every source (~50 KB for 400 sources, ~2 MB for
14,000), which every streaming session fetched once a second. Where the server gives no strong
validator (no ETag, a weak one, HEAD refused, or an ETag whose Last-Modified is too recent to
tell a rewrite in the same second), the check GETs and hashes ``zarr.json`` as before. A
replaced, rewritten or deleted store is seen either way; a transport failure stays one.

The servers here count the requests and bytes they answer: the controls are the same checks
through a server without ETag (every check a GET of ``zarr.json``, what every server cost before).
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from email.utils import formatdate
from functools import partial
from http.server import ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import RangeHandler

import tiler.location_keys as keys_mod
from tiler.errors import StoreChangedError, StoreUnavailableError
from tiler.location import Location
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile

HOUR = 3600.0


class _Handler(RangeHandler):
    """RangeHandler (byte ranges) answering HEAD too, with a Last-Modified and an ETag of
    kind ``etag``: ``content`` (a hash of the bytes, as S3's MD5), ``nginx`` (the mtime in hex
    seconds and the size), ``lighttpd`` (a hash of inode, size and mtime in whole seconds),
    ``weak`` (``W/``) or None; ``head=False``: HEAD not served (501).
    Every answer is logged in ``log`` as (method, path, bytes sent)."""

    etag: str | None = "content"
    head = True
    log: list[list]
    _code = 0

    def setup(self) -> None:
        super().setup()
        raw, handler = self.wfile, self

        class _Counting:
            def write(self, b):  # noqa: ANN001
                handler._entry[2] += len(b)  # (counted before the client can see it)
                return raw.write(b)

            def __getattr__(self, name: str):  # noqa: ANN204 (flush, close, closed)
                return getattr(raw, name)

        self._entry = ["", "", 0]
        self.wfile = _Counting()

    def _logged(self, answer) -> None:  # noqa: ANN001
        self._entry = [self.command, self.path, 0]
        self.log.append(self._entry)  # (before answering: logged when the client has it)
        answer()

    def send_response(self, code: int, message: str | None = None) -> None:
        self._code = code
        super().send_response(code, message)

    def end_headers(self) -> None:
        path = self.translate_path(self.path)
        if self._code < 300 and os.path.isfile(path):
            st = os.stat(path)
            self.send_header("Last-Modified", self.date_time_string(st.st_mtime))
            if self.etag == "content":
                with open(path, "rb") as f:
                    digest = hashlib.blake2b(f.read(), digest_size=8).hexdigest()
                self.send_header("ETag", f'"{digest}"')
            elif self.etag == "nginx":
                self.send_header("ETag", f'"{int(st.st_mtime):x}-{st.st_size:x}"')
            elif self.etag == "lighttpd":
                text = f"{st.st_ino}-{st.st_size}-{int(st.st_mtime)}".encode()
                self.send_header("ETag", f'"{hashlib.blake2b(text, digest_size=4).hexdigest()}"')
            elif self.etag == "weak":
                self.send_header("ETag", f'W/"{int(st.st_mtime):x}"')
        super().end_headers()

    def do_GET(self) -> None:  # noqa: N802 (http.server API)
        self._logged(super().do_GET)

    def do_HEAD(self) -> None:  # noqa: N802 (http.server API)
        if not self.head:
            self._logged(lambda: self.send_error(501))
            return

        def answer() -> None:
            if self._faulty():
                return
            path = self.translate_path(self.path)
            if not os.path.isfile(path):
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Length", str(os.path.getsize(path)))
            self.send_header("Accept-Ranges", "bytes")
            self.end_headers()

        self._logged(answer)


class _Serve:
    """``with _Serve(directory, etag=...) as srv:`` ``srv.url``, ``srv.log``, ``srv.handler``."""

    def __init__(self, directory: Path, *, etag: str | None = "content", head: bool = True):
        self.log: list[list] = []
        self.handler = type(
            "H",
            (_Handler,),
            {
                "etag": etag,
                "head": head,
                "log": self.log,
                "stall": threading.Event(),
                "release": threading.Event(),
            },
        )
        self._server = ThreadingHTTPServer(
            ("127.0.0.1", 0), partial(self.handler, directory=str(directory))
        )
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}"

    def __enter__(self) -> _Serve:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def root_answers(self, name: str = "s.zarr") -> list[tuple[str, int]]:
        """(method, bytes) of every answer for ``name``'s root zarr.json so far."""
        return [(m, n) for m, p, n in self.log if p == f"/{name}/zarr.json"]


def _tile(tmp: Path, name: str, seed: int) -> Path:
    src = write_dem(tmp / f"{name}.tif", fractal((65, 65), seed), cell=10.0)
    dst = tmp / f"{name}.zarr"
    tile(src, dst, TileOptions(block_size=33, workers=1, executor="threads"))
    return dst


def _age(store: Path, seconds: float = HOUR) -> None:
    """Date the store's zarr.json ``seconds`` back (a store written a while ago)."""
    t = time.time() - seconds
    os.utime(store / "zarr.json", (t, t))


@pytest.fixture
def root(tmp_path):
    """``s.zarr`` (served) and ``b.zarr`` (other heights, another generation), both dated an
    hour back."""
    for name, seed in (("s", 5), ("b", 6)):
        _age(_tile(tmp_path, name, seed))
    return tmp_path


def _replace(root: Path) -> None:
    os.rename(root / "s.zarr", root / "old.zarr")
    os.rename(root / "b.zarr", root / "s.zarr")


def _checks(st: TerrainStore, srv: _Serve, n: int = 3) -> list[tuple[str, int]]:
    """The root zarr.json answers of ``n`` forced checks of ``st``."""
    del srv.log[:]
    for _ in range(n):
        st.check_unchanged(force=True)
    return srv.root_answers()


# ---- (1) a check costs a HEAD, not the whole zarr.json ---------------------------------------
def test_a_check_through_an_etag_costs_no_get_of_the_root_metadata(root):
    size = (root / "s.zarr" / "zarr.json").stat().st_size
    with _Serve(root, etag="content") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        st.read_block((0, 0))
        answers = _checks(st, srv)
    assert [m for m, _ in answers] == ["HEAD"] * 3, answers
    assert all(n < 1000 < size for _, n in answers), (answers, size)  # headers only


def test_control_a_server_without_etag_costs_a_get_per_check(root):
    """The control: what every check cost before, and still costs here (the count sees GETs)."""
    size = (root / "s.zarr" / "zarr.json").stat().st_size
    with _Serve(root, etag=None) as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        st.read_block((0, 0))
        answers = _checks(st, srv)
    # no strong validator is remembered from the first HEAD (at open): a GET per check
    assert [m for m, _ in answers] == ["GET"] * 3, answers
    assert all(n > size for _, n in answers), (answers, size)


@pytest.mark.parametrize(
    ("etag", "head"),
    [("weak", True), ("nginx", True), ("content", False)],
    ids=["weak-etag", "nginx-etag", "head-refused"],
)
def test_no_strong_validator_falls_back_to_a_get(root, etag, head):
    """A weak ETag, nginx's (its Last-Modified and size, nothing more) or a server refusing
    HEAD: every check GETs zarr.json (one HEAD at first), and sees a replacement."""
    with _Serve(root, etag=etag, head=head) as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        assert [m for m, _ in srv.root_answers()][:2] == ["HEAD", "GET"]
        assert [m for m, _ in _checks(st, srv)] == ["GET"] * 3
        _replace(root)
        with pytest.raises(StoreChangedError, match="replaced or rewritten"):
            st.check_unchanged(force=True)


# ---- (2) a replaced store is still seen --------------------------------------------------------
@pytest.mark.parametrize("etag", ["content", "lighttpd", "nginx", None])
def test_a_replaced_store_is_seen(root, etag):
    with _Serve(root, etag=etag) as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        st.read_block((0, 0))
        st.check_unchanged(force=True)  # unchanged: quiet
        _replace(root)
        del srv.log[:]
        with pytest.raises(StoreChangedError, match="replaced or rewritten"):
            st.check_unchanged(force=True)
        with pytest.raises(StoreChangedError):
            st.read_block((0, 0))
        methods = [m for m, _ in srv.root_answers()]
    # seen through the validator (then zarr.json is read, for its generation) or by GET
    assert methods[0] == ("HEAD" if etag in ("content", "lighttpd") else "GET"), methods


def test_a_deleted_store_is_seen(root):
    with _Serve(root, etag="content") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        os.rename(root / "s.zarr", root / "gone.zarr")
        with pytest.raises(StoreChangedError, match="replaced or rewritten"):
            st.check_unchanged(force=True)


def test_a_rewrite_of_the_same_generation_drops_the_kept_shard_indexes(root):
    """A repair's rewrite (new bytes, same generation): no error, and the kept shard indexes
    are dropped (they may point at moved chunks) — seen through the ETag alone."""
    path = root / "s.zarr" / "zarr.json"
    with _Serve(root, etag="content") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        st.read_block((0, 0))
        epoch = st.shard_indexes.epoch
        st.check_unchanged(force=True)
        assert st.shard_indexes.epoch == epoch  # unchanged: kept
        doc = json.loads(path.read_bytes())
        path.write_text(json.dumps(doc, indent=4))  # same content, other bytes
        _age(root / "s.zarr")
        del srv.log[:]
        st.check_unchanged(force=True)
        assert st.shard_indexes.epoch == epoch + 1
        assert srv.root_answers()[0][0] == "HEAD"
        st.read_block((0, 0))  # reads on
        st.check_unchanged(force=True)
        assert st.shard_indexes.epoch == epoch + 1  # seen once


# ---- (3) ETags made of a time in whole seconds -------------------------------------------------
def _same_size_other_bytes(data: bytes) -> bytes:
    """``data`` (a zarr.json) with one character of its generation changed: the same size."""
    out = bytearray(data)
    i = out.index(b'"generation": "') + len(b'"generation": "')
    out[i] = ord("0") if out[i] != ord("0") else ord("1")
    return bytes(out)


@pytest.mark.parametrize("guard", [True, False], ids=["fresh-get", "control-trusted"])
def test_an_etag_too_recent_to_tell_a_same_second_rewrite_is_not_trusted(
    tmp_path, monkeypatch, guard
):
    """lighttpd's ETag (inode, size, mtime in seconds) of a zarr.json written just now does
    not change on a rewrite in place of the same size within that second: such a token is a
    GET and hash until the Last-Modified is FRESH_VALIDATOR_S old. The control: trusting it
    (no margin) misses the rewrite."""
    path = _tile(tmp_path, "s", 5) / "zarr.json"
    if not guard:
        monkeypatch.setattr(keys_mod, "FRESH_VALIDATOR_S", -HOUR)
    with _Serve(tmp_path, etag="lighttpd") as srv:
        loc = Location(f"{srv.url}/s.zarr")
        before = loc.change_token()
        st = os.stat(path)
        path.write_bytes(_same_size_other_bytes(path.read_bytes()))  # (same inode)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))  # (the same second)
        after = loc.change_token()
        methods = [m for m, _ in srv.root_answers()]
    if guard:
        assert before != after
        assert methods == ["HEAD", "GET", "HEAD", "GET"], methods
    else:
        assert before == after  # the rewrite unseen: what the margin is for
        assert methods == ["HEAD", "HEAD"], methods


@pytest.mark.parametrize("guard", [True, False], ids=["nginx-get", "control-trusted"])
def test_an_older_store_renamed_over_is_seen_through_nginx(root, monkeypatch, guard):
    """nginx's ETag is the Last-Modified and the size: a zarr.json of the same size and the
    same mtime second (two stores tiled in the same second) renamed into place keeps it, so
    it is not used as a token. The control: trusting it misses the replacement."""
    if not guard:
        monkeypatch.setattr(keys_mod, "_mtime_etag", lambda *a: False)
    path = root / "s.zarr" / "zarr.json"
    other = root / "b.zarr" / "zarr.json"
    other.write_bytes(_same_size_other_bytes(path.read_bytes()))
    st = os.stat(path)
    os.utime(other, ns=(st.st_atime_ns, st.st_mtime_ns))
    with _Serve(root, etag="nginx") as srv:
        reader = TerrainStore(f"{srv.url}/s.zarr")
        os.replace(other, path)
        if guard:
            with pytest.raises(StoreChangedError, match="replaced or rewritten"):
                reader.check_unchanged(force=True)
        else:
            reader.check_unchanged(force=True)  # unseen


def test_a_fresh_store_is_checked_by_get_then_by_head_once_settled(root):
    """A zarr.json written moments ago is hashed; once settled its ETag is used (the change of
    token kind rereads the generation once: no error)."""
    _age(root / "s.zarr", 0.0)
    with _Serve(root, etag="lighttpd") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        assert [m for m, _ in _checks(st, srv, 1)] == ["HEAD", "GET"]
        _age(root / "s.zarr")
        st.check_unchanged(force=True)  # token kind changes: generation reread, same store
        assert [m for m, _ in _checks(st, srv, 2)] == ["HEAD", "HEAD"]


def test_settled_reads_http_dates():
    now = time.time()
    assert keys_mod._settled(formatdate(now - HOUR, usegmt=True), formatdate(now, usegmt=True))
    assert not keys_mod._settled(formatdate(now, usegmt=True), formatdate(now, usegmt=True))
    assert keys_mod._settled(formatdate(now - HOUR, usegmt=True), None)  # (this clock)
    assert not keys_mod._settled("yesterday", formatdate(now, usegmt=True))


# ---- transport failures stay transport failures ------------------------------------------------
def test_a_head_answered_503_is_unavailable_not_a_change(root):
    with _Serve(root, etag="content") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        srv.handler.fail_scope, srv.handler.fail_status = "all", 503
        with pytest.raises(StoreUnavailableError, match="503"):
            st.check_unchanged(force=True)
        srv.handler.fail_status = None
        st.check_unchanged(force=True)  # the store is the same: no StoreChangedError latched
        assert st.read_block((0, 0)).size


def test_a_server_gone_is_unavailable_not_a_change(root):
    srv = _Serve(root, etag="content")
    with srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
    with pytest.raises(StoreUnavailableError):
        st.check_unchanged(force=True)


# ---- S3 (moto) ---------------------------------------------------------------------------------
moto_server = pytest.importorskip("moto.server")
s3fs = pytest.importorskip("s3fs")


@pytest.fixture(scope="module")
def s3_endpoint():
    """A moto S3 server on loopback for this module."""
    import logging

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_s3_token_is_the_etag_and_sees_a_replacement(tmp_path, s3_endpoint, monkeypatch):
    """On S3 the token is head_object's ETag (no GET of zarr.json: ``get_bytes`` is not
    called), which changes when zarr.json is replaced, and is None once it is deleted. The
    control: the token by GET (what it was) does call ``get_bytes``."""
    for k in ("AWS_PROFILE", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_endpoint)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    s3fs.S3FileSystem.clear_instance_cache()
    bucket = f"audit46-{int(time.time() * 1000) % 10**8}"
    fs = s3fs.S3FileSystem()
    fs.mkdir(bucket)
    a, b = _tile(tmp_path, "a", 5), _tile(tmp_path, "b", 6)
    fs.put(str(a / "zarr.json"), f"{bucket}/s.zarr/zarr.json")
    loc = Location(f"s3://{bucket}/s.zarr")
    gets: list[str] = []
    real_get = Location.get_bytes
    monkeypatch.setattr(
        Location, "get_bytes", lambda self, key: gets.append(key) or real_get(self, key)
    )
    t0 = loc.change_token()
    assert t0 == loc.change_token() and t0[0] == "etag"
    assert gets == []  # no GET of zarr.json
    fs.put(str(b / "zarr.json"), f"{bucket}/s.zarr/zarr.json")
    t1 = loc.change_token()
    assert t1 != t0 and gets == []
    fs.rm(f"{bucket}/s.zarr/zarr.json")
    assert loc.change_token() is None
    # the control: without a validator the token is a GET of zarr.json
    loc._no_validator = True
    fs.put(str(a / "zarr.json"), f"{bucket}/s.zarr/zarr.json")
    assert isinstance(loc.change_token(), bytes) and gets == ["zarr.json"]


def test_a_store_reads_through_the_etag_server(root):
    """(smoke) The test server serves a store as a local read sees it."""
    with _Serve(root, etag="content") as srv:
        st = TerrainStore(f"{srv.url}/s.zarr")
        ref = TerrainStore(root / "s.zarr")
        assert np.array_equal(st.read_block((1, 1)), ref.read_block((1, 1)))
