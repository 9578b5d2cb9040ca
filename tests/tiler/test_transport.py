"""A server's failure is not the store's damage: classification, HTTP read timeouts, wording."""

from __future__ import annotations

import time

import aiohttp
import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

from tiler.errors import (
    BlockDataError,
    ChunkChecksumError,
    StorageOptionsError,
    StoreUnavailableError,
)
from tiler.location import Location
from tiler.store import TerrainStore
from tiler.tile import TileOptions, tile
from tiler.transport import HTTP_TIMEOUT_S, http_options, is_transport_error


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    d = tmp_path_factory.mktemp("transport")
    src = write_dem(d / "d.tif", fractal((129, 129), 5), cell=10.0)
    tile(src, d / "s.zarr", TileOptions(block_size=65, workers=1))
    return d


# -- pure ---------------------------------------------------------------------------------


def test_transport_errors_are_told_from_damage():
    import obstore.exceptions as oe

    url = aiohttp.client.URL("http://x/k")
    req = aiohttp.RequestInfo(url, "GET", {}, url)
    for exc in (
        TimeoutError(),
        ConnectionResetError("reset"),
        aiohttp.ServerDisconnectedError(),
        aiohttp.SocketTimeoutError("Timeout on reading data from socket"),
        aiohttp.ClientResponseError(req, (), status=503, message="Service Unavailable"),
        oe.GenericError("Generic S3 error: error sending request"),
    ):
        assert is_transport_error(exc), exc
    # damage and bugs are not the network's: the control
    for exc in (
        ValueError("checksum mismatch"),
        RuntimeError("blosc decompression error"),
        OSError(5, "Input/output error"),
        FileNotFoundError("gone"),
        oe.NotFoundError("no such key"),
        ZeroDivisionError(),
    ):
        assert not is_transport_error(exc), exc


def test_http_options_default_and_override_timeouts():
    t = http_options(None)["client_kwargs"]["timeout"]
    assert (t.total, t.sock_read, t.sock_connect) == (None, HTTP_TIMEOUT_S, HTTP_TIMEOUT_S)
    t = http_options({"timeout": 2.5, "headers": {"a": "b"}})
    assert t["client_kwargs"]["timeout"].sock_read == 2.5 and "timeout" not in t
    assert t["headers"] == {"a": "b"}  # other options pass through
    own = aiohttp.ClientTimeout(total=7)
    assert http_options({"client_kwargs": {"timeout": own}})["client_kwargs"]["timeout"] is own


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "5", True, None])
def test_a_bad_timeout_option_is_refused_naming_it(bad):
    with pytest.raises(StorageOptionsError, match="'timeout' must be a number of seconds > 0"):
        Location("http://127.0.0.1:1/s.zarr", {"timeout": bad})


# -- over a loopback server ------------------------------------------------------------------


def test_a_503_is_the_server_failing_not_damage(root):
    srv = LoopbackServer(root)
    with srv as url:
        s = TerrainStore(f"{url}/s.zarr")
        np.testing.assert_array_equal(s.read_level_raw((0, 0), 1), s.read_level_raw((0, 0), 1))
        srv.handler.fail_status = 503
        with pytest.raises(StoreUnavailableError) as e:
            s.read_level_raw((0, 0), 2)
    msg = str(e.value)
    assert "503" in msg and "the server or the network failed, not the store" in msg
    assert "verify" not in msg and (e.value.block, e.value.level) == ((0, 0), 2)
    assert not isinstance(e.value, BlockDataError)


def test_damage_over_http_is_still_damage(root, tmp_path):
    """The control: a flipped byte served without a fault is a checksum error, not the server's."""
    import shutil

    shutil.copytree(root / "s.zarr", tmp_path / "s.zarr")
    chunk = next(p for p in (tmp_path / "s.zarr" / "levels" / "5" / "c").rglob("*") if p.is_file())
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    chunk.write_bytes(bytes(raw))
    with LoopbackServer(tmp_path) as url:
        s = TerrainStore(f"{url}/s.zarr")
        blocks = [tuple(b) for b in np.argwhere(s.index.exists)]
        errors = []
        for b in blocks:
            try:
                s.read_level_raw(b, 5)
            except Exception as exc:  # noqa: BLE001 - collected and checked below
                errors.append(exc)
    assert errors and all(isinstance(e, ChunkChecksumError) for e in errors), errors
    assert "verify" in str(errors[0])


def test_a_server_that_stops_answering_times_out_as_unavailable(root):
    srv = LoopbackServer(root)
    with srv as url:
        s = TerrainStore(Location(f"{url}/s.zarr", {"timeout": 2.0}))
        s.read_level_raw((0, 0), 0)
        srv.stall.set()  # accepts connections, never answers (a SIGSTOPped server)
        t0 = time.monotonic()
        with pytest.raises(StoreUnavailableError, match="did not answer in time") as e:
            s.read_level_raw((0, 1), 3)
        took = time.monotonic() - t0
    assert took < 5.0, took  # aiohttp's own default waited 300 s
    assert isinstance(e.value.__cause__, TimeoutError) and "'timeout'" in str(e.value)


def test_verify_over_a_failing_server_concludes_nothing(root):
    """`verify` over a server answering 503 raised aiohttp's error (and a timeout was counted
    as a damaged chunk); now it stops with StoreUnavailableError. The control: the healthy
    server verifies clean."""
    from tiler.verify import verify_store

    srv = LoopbackServer(root)
    with srv as url:
        assert verify_store(f"{url}/s.zarr").ok
        srv.handler.fail_status = 503
        with pytest.raises(StoreUnavailableError, match="verify stopped: nothing was concluded"):
            verify_store(f"{url}/s.zarr")


@pytest.mark.parametrize(
    ("match", "subject"),
    [(None, "the store's metadata"), ("/c/", "the block index")],
    ids=["metadata", "index"],
)
def test_opening_over_a_failing_server_is_unavailable_not_damage(root, match, subject):
    """A 503 for the root metadata (or the block index's chunks) raised aiohttp's error when a
    store was opened (and the index's was worded "the store is damaged")."""
    srv = LoopbackServer(root)
    with srv as url:
        TerrainStore(f"{url}/s.zarr").index  # noqa: B018 - the control: a healthy server
        srv.handler.fail_status, srv.handler.fail_scope, srv.handler.fail_match = 503, "all", match
        with pytest.raises(StoreUnavailableError, match=f"cannot fetch {subject}") as e:
            TerrainStore(f"{url}/s.zarr").index  # noqa: B018 - read when first used
    assert "503" in str(e.value) and "damaged" not in str(e.value)


def test_a_refused_access_is_not_damage(root):
    """s3fs turns a 403 into PermissionError, which was worded "the store is damaged: verify
    it"; a 403 over HTTP and a PermissionError now say access was refused."""
    from tiler.transport import advice

    assert is_transport_error(PermissionError(13, "Forbidden"))
    assert advice(PermissionError(13, "Forbidden")).startswith("access was refused")
    assert "access" not in advice(TimeoutError())  # the control
    srv = LoopbackServer(root)
    with srv as url:
        s = TerrainStore(f"{url}/s.zarr")
        srv.handler.fail_status = 403
        with pytest.raises(StoreUnavailableError, match="403.*access was refused") as e:
            s.read_level_raw((0, 0), 2)
    assert "verify" not in str(e.value)
