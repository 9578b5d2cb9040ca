"""Stores on S3: tile, info, export, stream, render against moto's S3 server on loopback.

The server is started by the fixture on 127.0.0.1 (a free port) and stopped after the module;
every test uses its own bucket. Credentials and endpoint come either from the environment
(AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, ...) or from ``--storage-options`` JSON.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from typer.testing import CliRunner

from tests.demtools import fractal, write_dem
from tests.render.shared_gl import gl_context
from tests.tiler.storetools import VOLATILE
from tiler import tile as tile_mod
from tiler.errors import StorageOptionsError, StoreLockedError
from tiler.location import Location, parse_storage_options
from tiler.tile import TileOptions, tile

moto_server = pytest.importorskip("moto.server")
s3fs = pytest.importorskip("s3fs")

# s3fs caches filesystems whose aiohttp sessions are closed by the garbage collector
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")

CREDS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing"}
ENV_KEYS = (*CREDS, "AWS_ENDPOINT_URL", "AWS_DEFAULT_REGION", "AWS_SESSION_TOKEN")


@pytest.fixture(scope="module")
def s3_server():
    """``http://127.0.0.1:<port>`` of a moto S3 server running for this module."""
    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one line per request otherwise
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    assert host == "127.0.0.1"
    yield f"http://{host}:{port}"
    server.stop()


_N = [0]


@pytest.fixture
def bucket(s3_server, monkeypatch) -> str:
    """A fresh bucket; the environment points fsspec/s3fs at the loopback server."""
    for k in ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    for k, v in CREDS.items():
        monkeypatch.setenv(k, v)
    s3fs.S3FileSystem.clear_instance_cache()
    _N[0] += 1
    name = f"terrastream-test-{_N[0]}-{int(time.time() * 1000) % 10**8}"
    s3fs.S3FileSystem().mkdir(name)
    return name


def _dem(tmp_path: Path, nodata: bool = True) -> Path:
    data = fractal((130, 150), seed=5)
    if nodata:
        data[20:50, 30:80] = -9999
    return write_dem(tmp_path / "dem.tif", data, nodata=-9999 if nodata else None)


def _objects(url: str, **so) -> dict[str, bytes]:
    loc = Location(url, so or None)
    out = {}
    for key in loc.list_keys():
        data = loc.get_bytes(key)
        if key == "zarr.json":
            doc = json.loads(data)
            for name in VOLATILE:
                doc["attributes"]["terrastream"].pop(name, None)
            data = json.dumps(doc, sort_keys=True).encode()
        out[key] = data
    return out


def _local(root: Path) -> dict[str, bytes]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            key = p.relative_to(root).as_posix()
            data = p.read_bytes()
            if key == "zarr.json":
                doc = json.loads(data)
                for name in VOLATILE:
                    doc["attributes"]["terrastream"].pop(name, None)
                data = json.dumps(doc, sort_keys=True).encode()
            out[key] = data
    return out


def _cli(*args: str, env: dict | None = None):
    from cli.main import app

    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def test_cli_tile_info_export_roundtrip_env(tmp_path, bucket):
    """tile → info → export on s3:// with the endpoint and keys from the environment: the
    objects equal a local store's files, the export equals the source bit for bit."""
    src = _dem(tmp_path)
    url = f"s3://{bucket}/dem.zarr"
    r = _cli("tile", src, url, "--block-size", "33", "--workers", "2")
    assert r.exit_code == 0, r.output
    local = tmp_path / "local.zarr"
    tile(src, local, TileOptions(block_size=33, workers=1, executor="threads"))
    remote_objects = _objects(url)
    assert remote_objects.keys() == _local(local).keys()
    assert remote_objects == _local(local)
    r = _cli("info", url, "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["url"] == url and d["checksums"] == "crc32c on every chunk"
    out = tmp_path / "back.tif"
    r = _cli("export", url, out, "--format", "gtiff")
    assert r.exit_code == 0, r.output
    with rasterio.open(src) as a, rasterio.open(out) as b:
        assert np.array_equal(a.read(1), b.read(1))
        assert a.nodata == b.nodata


def test_storage_options_json(tmp_path, bucket, s3_server, monkeypatch):
    """No AWS_* in the environment: the endpoint and keys come from --storage-options."""
    for k in ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    s3fs.S3FileSystem.clear_instance_cache()
    so = json.dumps({"endpoint_url": s3_server, "key": "testing", "secret": "testing"})
    src = _dem(tmp_path, nodata=False)
    url = f"s3://{bucket}/opts.zarr"
    r = _cli("tile", src, url, "--block-size", "65", "--storage-options", so)
    assert r.exit_code == 0, r.output
    r = _cli("info", url, "--json", "--storage-options", so)
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["block_size"] == 65
    out = tmp_path / "o.tif"
    r = _cli("export", url, out, "--storage-options", so)
    assert r.exit_code == 0, r.output
    with rasterio.open(src) as a, rasterio.open(out) as b:
        assert np.array_equal(a.read(1), b.read(1))
    # positive controls: a wrong endpoint fails (exit 1), bad JSON is a usage error (exit 2)
    s3fs.S3FileSystem.clear_instance_cache()
    bad = json.dumps({"endpoint_url": "http://127.0.0.1:9", "key": "testing", "secret": "x"})
    r = _cli("info", url, "--storage-options", bad)
    assert r.exit_code != 0
    r = _cli("info", url, "--storage-options", "{endpoint_url: nope")
    assert r.exit_code == 2 and "--storage-options" in r.output and "JSON object" in r.output
    r = _cli("info", str(tmp_path), "--storage-options", so)
    assert r.exit_code == 2 and "apply to URLs" in r.output


@pytest.mark.parametrize("wrapped", [True, False], ids=["named", "control"])
def test_tile_to_a_dead_endpoint_blames_the_server(tmp_path, monkeypatch, wrapped):
    """Nothing listens at the endpoint: `tile` exits 1 saying the server or the network
    failed (its first contact with the destination is classified). The control, without the
    classification, gives the client's bare error."""
    import contextlib

    for k in ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    if not wrapped:
        monkeypatch.setattr(tile_mod, "server_errors", lambda *a: contextlib.nullcontext())
    s3fs.S3FileSystem.clear_instance_cache()
    dead = {"endpoint_url": "http://127.0.0.1:9", "key": "testing", "secret": "x",
            "config_kwargs": {"retries": {"max_attempts": 1}}}  # fmt: skip
    r = _cli("tile", _dem(tmp_path, nodata=False), "s3://b/dead.zarr", "--storage-options",
             json.dumps(dead))  # fmt: skip
    assert r.exit_code == 1, r.output
    assert "Could not connect to the endpoint URL" in r.output
    blamed = "the server or the network failed, not the store" in r.output
    assert blamed == wrapped, r.output


def test_parse_storage_options():
    assert parse_storage_options(None) is None and parse_storage_options("  ") is None
    assert parse_storage_options('{"anon": true}') == {"anon": True}
    for bad in ("[1, 2]", "nope", '"s"'):
        with pytest.raises(StorageOptionsError, match="JSON object"):
            parse_storage_options(bad)
    with pytest.raises(StorageOptionsError, match="apply to URLs"):
        Location("local/x.zarr", {"anon": True})  # options on a local path
    loc = Location("s3://b/x.zarr", {"anon": True})
    import pickle

    assert pickle.loads(pickle.dumps(loc.for_workers())).storage_options == {"anon": True}


def test_stream_and_render_on_s3(tmp_path, bucket, request):
    """A session on the S3 store loads every visible block of a fly-through (waiting for each
    frame: no stall), the CLI stream runs, and render draws a frame from S3."""
    from streamer.run import make_path
    from streamer.session import open_session
    from tiler.store import open_store

    src = write_dem(tmp_path / "big.tif", fractal((257, 257), seed=9))
    url = f"s3://{bucket}/stream.zarr"
    tile(src, url, TileOptions(block_size=65, workers=2))
    store = open_store(url)
    cams = make_path(store, "default", frames=12, fps=30.0, viewport=(160, 120))
    stalled = []
    loaded = 0
    with open_session(store, budget_mb=64, workers=2) as session:
        for cam in cams:
            frame = session.update(cam, 1 / 30, wait=True)
            stalled.append(frame.stats.stalled)
            loaded += frame.stats.visible_blocks
    assert loaded > 0 and not any(stalled)
    out = tmp_path / "run.json"
    r = _cli("stream", url, "--frames", "10", "--json", out)
    assert r.exit_code == 0, r.output
    assert len(json.loads(out.read_text())["frames"]) == 10
    if request.config.getoption("-m", default="") == "not gl":
        return
    gl_context()  # no GL: skip the render half with the reason (CI=true: fail instead)
    png = tmp_path / "v.png"
    r = _cli("render", url, "--size", "64x48", "-o", png, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["triangles"] > 0 and png.stat().st_size > 0


def test_two_writers_second_refused(tmp_path, bucket, monkeypatch):
    """While one tile() writes into s3://..., a second one is refused naming the lease."""
    src = _dem(tmp_path, nodata=False)
    url = f"s3://{bucket}/two.zarr"
    started, release = threading.Event(), threading.Event()
    original = tile_mod.process_block

    def slow(window, params):
        started.set()
        release.wait(60)
        return original(window, params)

    monkeypatch.setattr(tile_mod, "process_block", slow)
    box: dict = {}

    def first() -> None:
        try:
            box["store"] = tile(src, url, TileOptions(block_size=65, workers=1))
        except BaseException as exc:  # noqa: BLE001 - checked below
            box["error"] = exc

    t = threading.Thread(target=first, name="test-first-writer")
    t.start()
    try:
        assert started.wait(60)
        monkeypatch.setattr(tile_mod, "process_block", original)
        with pytest.raises(StoreLockedError, match="lease|being written|writer") as ei:
            tile(src, url, TileOptions(block_size=65, workers=1))
        assert url in str(ei.value)
    finally:
        release.set()
        t.join(120)
    assert "error" not in box, box.get("error")
    assert box["store"].meta.complete


def test_dask_workers_write_to_s3(tmp_path, bucket):
    """Dask tasks write their chunks to S3 themselves; the store equals the local one."""
    distributed = pytest.importorskip("distributed")
    src = _dem(tmp_path)
    url = f"s3://{bucket}/dask.zarr"
    local = tmp_path / "local.zarr"
    tile(src, local, TileOptions(block_size=33, workers=1, executor="threads"))
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        store = tile(src, url, TileOptions(block_size=33, scheduler=cluster.scheduler_address))
    assert store.tile_summary.executor == "dask"
    assert _objects(url) == _local(local)


def test_reads_use_obstore_by_default_and_fsspec_on_request(
    tmp_path, bucket, s3_server, monkeypatch
):
    """s3:// reads go through zarr's ObjectStore (obstore; measured faster, see
    bench/results/s3_reads.json); TERRASTREAM_S3_READER=fsspec and options only s3fs knows
    fall back to fsspec; both read the same values."""
    pytest.importorskip("obstore")
    from tiler.s3_reader import S3_READER_ENV, open_s3_reader
    from tiler.store import TerrainStore, open_store

    src = _dem(tmp_path)
    url = f"s3://{bucket}/r.zarr"
    tile(src, url, TileOptions(block_size=33, workers=1))
    monkeypatch.delenv(S3_READER_ENV, raising=False)
    a = open_store(url)
    assert type(a._group.store).__name__ == "ObjectStore"
    monkeypatch.setenv(S3_READER_ENV, "fsspec")
    b = open_store(url)
    assert type(b._group.store).__name__ == "FsspecStore"
    z = TerrainStore(url, direct_reads=False)  # zarr's reads: the reference
    assert a.direct_reads and b.direct_reads and not z.direct_reads  # (tiler.chunkread_remote)
    for blk in list(a.blocks())[:5]:
        assert np.array_equal(a.read_block(blk), b.read_block(blk))
        assert np.array_equal(a.read_block(blk), z.read_block(blk))
        assert np.array_equal(a.read_block(blk, 3), z.read_block(blk, 3))
    assert open_s3_reader(url, {"profile": "x"}) is None  # only s3fs knows profiles
    # endpoint and keys from storage options alone (no AWS_* variables)
    monkeypatch.delenv(S3_READER_ENV)
    for k in ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    so = {"endpoint_url": s3_server, "key": "testing", "secret": "testing",
          "client_kwargs": {"region_name": "us-east-1"}}  # fmt: skip
    c = open_store(Location(url, so))
    assert type(c._group.store).__name__ == "ObjectStore"
    blk = next(iter(a.blocks()))
    assert np.array_equal(a.read_block(blk), c.read_block(blk))


@pytest.mark.parametrize("reader", ["obstore", "fsspec"])
def test_an_s3_server_that_goes_away_is_unavailable_not_damage(tmp_path, monkeypatch, reader):
    """Reads after the S3 server stopped raise StoreUnavailableError naming the block (obstore
    raised its GenericError and s3fs botocore's EndpointConnectionError, which sessions took
    for bugs); a read before it stopped is the control."""
    from tiler.errors import StoreUnavailableError
    from tiler.s3_reader import S3_READER_ENV
    from tiler.store import open_store

    if reader == "obstore":
        pytest.importorskip("obstore")
    own = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    own.start()
    try:
        host, port = own.get_host_and_port()
        for k in ENV_KEYS:
            monkeypatch.delenv(k, raising=False)
        monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://{host}:{port}")
        monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
        for k, v in CREDS.items():
            monkeypatch.setenv(k, v)
        monkeypatch.setenv(S3_READER_ENV, reader)
        s3fs.S3FileSystem.clear_instance_cache()
        s3fs.S3FileSystem().mkdir(f"terrastream-gone-{reader}")
        url = f"s3://terrastream-gone-{reader}/g.zarr"
        tile(_dem(tmp_path, nodata=False), url, TileOptions(block_size=33, workers=1))
        s = open_store(url)
        blocks = list(s.blocks())
        s.read_level_raw(blocks[0], 1)  # the control: the server answers
    finally:
        own.stop()
    with pytest.raises(StoreUnavailableError) as e:
        s.read_level_raw(blocks[1], 2)
    assert (e.value.block, e.value.level) == (tuple(blocks[1]), 2)
    msg = str(e.value)
    assert "the server or the network failed, not the store" in msg and "\n" not in msg


def test_a_tile_to_s3_ends_without_unclosed_session_errors(tmp_path, bucket):
    """A fresh process tiling to S3 exits cleanly: s3fs closes no asynchronous filesystem's
    client, so every such command ended with aiohttp's "ERROR asyncio: Unclosed client
    session" logged at exit (``tiler._s3fs.close_sessions`` closes them)."""
    import os
    import subprocess
    import sys

    cmd = [sys.executable, "-c", "from cli.main import main; main()", "tile",
           str(_dem(tmp_path)), f"s3://{bucket}/c.zarr", "--block-size", "65"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ), timeout=300)
    assert r.returncode == 0, r.stderr
    assert "wrote s3://" in r.stdout and "Unclosed client session" not in r.stderr, r.stderr
