"""How often an ``s3://`` request is tried before its failure reaches terrastream.

botocore's default retries (legacy, 5 attempts) under s3fs's own 5 made a server that drops
connections cost 25 connections per request (an ``open_store`` took 47 s) and obstore's default
(10 retries, up to 180 s) 11 connections and 20 s per read, before a session's own retries
could count one failure. The counts are measured against a loopback server that accepts each
connection and closes it without an answer; the controls set other retries and see the counts
follow them.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading

import pytest

from tiler.location import Location
from tiler.transport import S3FS_RETRIES, s3fs_options

s3fs = pytest.importorskip("s3fs")

# s3fs caches filesystems whose aiohttp sessions are closed by the garbage collector
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


@pytest.fixture
def dropping(monkeypatch):
    """``(endpoint, connections)``: a loopback server that reads each request and closes the
    connection without an answer; ``connections[0]`` counts them. The environment has test
    credentials and no AWS retry settings."""
    for k in ("AWS_ENDPOINT_URL", "AWS_SESSION_TOKEN", "AWS_MAX_ATTEMPTS", "AWS_RETRY_MODE"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(64)
    srv.settimeout(0.1)
    count, stop = [0], threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            count[0] += 1
            conn.settimeout(5)
            with contextlib.suppress(OSError):
                conn.recv(65536)
            conn.close()

    t = threading.Thread(target=serve, name="test-dropping-s3", daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.getsockname()[1]}", count
    stop.set()
    t.join(timeout=10)
    srv.close()
    assert not t.is_alive()


def test_s3fs_options_bound_botocores_retries_unless_set(monkeypatch):
    monkeypatch.delenv("AWS_MAX_ATTEMPTS", raising=False)
    monkeypatch.delenv("AWS_RETRY_MODE", raising=False)
    given = {"anon": True, "config_kwargs": {"connect_timeout": 5}}
    so = s3fs_options(given)
    assert so["config_kwargs"] == {"connect_timeout": 5, "retries": S3FS_RETRIES}
    assert given == {"anon": True, "config_kwargs": {"connect_timeout": 5}}  # not mutated
    assert s3fs_options(None) == {"config_kwargs": {"retries": S3FS_RETRIES}}
    own = {"config_kwargs": {"retries": {"mode": "adaptive"}}}
    assert s3fs_options(own) == own  # the user's retries win
    assert Location("s3://b/x.zarr").fsspec_options() == {
        "config_kwargs": {"retries": S3FS_RETRIES}
    }
    assert "config_kwargs" not in Location("https://h/x.zarr").fsspec_options()
    for var, value in (("AWS_MAX_ATTEMPTS", "7"), ("AWS_RETRY_MODE", "legacy")):
        with monkeypatch.context() as m:
            m.setenv(var, value)  # the environment's retries win too
            assert s3fs_options({"anon": True}) == {"anon": True}


def _cat(endpoint: str, so: dict) -> None:
    """One GET of a key through s3fs with the options a Location gives it."""
    import fsspec

    s3fs.S3FileSystem.clear_instance_cache()
    opts = Location("s3://b/x.zarr", {"endpoint_url": endpoint, **so}).fsspec_options()
    fs = fsspec.filesystem("s3", skip_instance_cache=True, **opts)
    with pytest.raises(Exception, match="Connection was closed"):
        fs.cat_file("b/x.zarr/zarr.json")


def test_a_dropping_server_gets_two_botocore_attempts_per_s3fs_try(dropping):
    """Default: 2 botocore attempts for each of s3fs's tries. The control: the user's one
    attempt gives half the connections (the count follows botocore's setting; botocore's own
    default made it 5 per try)."""
    endpoint, count = dropping
    _cat(endpoint, {})
    ours = count[0]
    count[0] = 0
    _cat(endpoint, {"config_kwargs": {"retries": {"mode": "standard", "total_max_attempts": 1}}})
    one = count[0]
    assert one >= 1 and ours == S3FS_RETRIES["total_max_attempts"] * one, (ours, one)


def _obstore_get(endpoint: str) -> None:
    from zarr.core.buffer import default_buffer_prototype

    from tiler.s3_reader import open_s3_reader

    store = open_s3_reader("s3://b/x.zarr", {"endpoint_url": endpoint})
    assert store is not None
    with pytest.raises(Exception, match="retries"):
        asyncio.run(store.get("zarr.json", default_buffer_prototype()))


def test_obstore_reads_retry_twice(dropping, monkeypatch):
    """One read: 1 + 2 retries (obstore's default: 1 + 10, 20 s). The control: 4 retries set
    in the same constant give 5 connections."""
    pytest.importorskip("obstore")
    import tiler.s3_reader as s3r

    endpoint, count = dropping
    _obstore_get(endpoint)
    assert count[0] == 1 + s3r.S3_READ_RETRY["max_retries"] == 3
    count[0] = 0
    monkeypatch.setitem(s3r.S3_READ_RETRY, "max_retries", 4)
    _obstore_get(endpoint)
    assert count[0] == 5


def test_a_store_being_written_keeps_five_attempts(monkeypatch, tmp_path):
    """``tile`` has no retries of its own around a chunk write, so its destination (and its
    workers, which get its options) keeps botocore's 5 attempts, in standard mode; a user's
    retries win there too, and other locations are left as they are."""
    import tiler.tile as tile_mod
    from tiler.location import for_writing
    from tiler.transport import S3FS_WRITE_RETRIES

    monkeypatch.delenv("AWS_MAX_ATTEMPTS", raising=False)
    monkeypatch.delenv("AWS_RETRY_MODE", raising=False)
    assert S3FS_WRITE_RETRIES["total_max_attempts"] == 5
    w = for_writing(Location("s3://b/x.zarr", {"anon": True}))
    assert w.fsspec_options()["config_kwargs"]["retries"] == S3FS_WRITE_RETRIES
    assert w.for_workers().fsspec_options() == w.fsspec_options()
    own = {"config_kwargs": {"retries": {"total_max_attempts": 9}}}
    assert for_writing(Location("s3://b/x.zarr", own)).storage_options == own
    local = Location(str(tmp_path / "x.zarr"))
    assert for_writing(local) is local
    seen = []

    def capture(plan, loc, opts, progress):
        seen.append(loc)
        raise RuntimeError("captured")

    monkeypatch.setattr(tile_mod, "_tile", capture)
    monkeypatch.setattr(tile_mod, "plan_source", lambda src, opts: None)
    with pytest.raises(RuntimeError, match="captured"):
        tile_mod.tile("dem.tif", "s3://b/x.zarr")
    assert seen[0].fsspec_options()["config_kwargs"]["retries"] == S3FS_WRITE_RETRIES
    # the control: a store opened to read gets the reader's 2 attempts
    assert Location("s3://b/x.zarr").fsspec_options()["config_kwargs"]["retries"] == S3FS_RETRIES


def _get(endpoint: str, **kw) -> None:
    """One ``get_bytes`` of a key through a Location (its s3fs filesystem and tries)."""
    s3fs.S3FileSystem.clear_instance_cache()
    with pytest.raises(Exception, match="Connection was closed"):
        Location("s3://b/x.zarr", {"endpoint_url": endpoint}, **kw).get_bytes("zarr.json")


def test_a_location_tries_each_request_s3fs_tries_times(dropping, monkeypatch):
    """A Location's s3fs filesystem tries each request ``S3FS_TRIES`` (2) times, each with
    botocore's 2 attempts. A failing ``get_bytes`` makes two s3fs requests here, so one try of
    each is 4 connections and ours 8; s3fs's own 5 tries made 20 and slept 1.9 s between
    them per request. The controls: 1 and 3 tries in the same constant give 4 and
    12."""
    import tiler.transport as tr

    endpoint, count = dropping
    seen = {}
    for tries in (tr.S3FS_TRIES, 1, 3):
        monkeypatch.setattr(tr, "S3FS_TRIES", tries)
        count[0] = 0
        _get(endpoint)
        seen[tries] = count[0]
    assert seen[1] == 2 * S3FS_RETRIES["total_max_attempts"]
    assert seen == {1: seen[1], 2: 2 * seen[1], 3: 3 * seen[1]}, seen


def test_readers_and_writers_get_their_own_filesystems(monkeypatch):
    """A store being written keeps s3fs's 5 tries and a reader gets 2, through every way a
    Location opens s3fs (raw keys, zarr), in filesystems fsspec caches apart; they pickle (a
    dask worker may receive one) with their tries."""
    import pickle

    from zarr.storage import FsspecStore

    from tiler._s3fs import ReadS3FileSystem, WriteS3FileSystem
    from tiler.location import for_writing
    from tiler.transport import S3FS_TRIES, S3FS_WRITE_TRIES

    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    assert (S3FS_TRIES, S3FS_WRITE_TRIES) == (2, 5)
    read = Location("s3://b/x.zarr", {"anon": True})
    write = for_writing(read)
    assert write.writing and not read.writing and write.for_workers().writing
    assert Location(write).writing  # a copy keeps it
    rfs, path = read._fs()
    wfs, _ = write._fs()
    assert (type(rfs), rfs.retries, path) == (ReadS3FileSystem, 2, "b/x.zarr")
    assert (type(wfs), wfs.retries) == (WriteS3FileSystem, 5)
    assert read._fs()[0] is rfs  # fsspec's instance cache still serves it
    s3fs.S3FileSystem.clear_instance_cache()  # clears them too (a new endpoint in the env)
    assert read._fs()[0] is not rfs
    store, kw = read.zarr_args("r")
    assert isinstance(store, FsspecStore) and kw == {} and store.read_only
    assert store.fs.retries == 2 and store.path == "b/x.zarr"
    assert read.zarr_args("r+")[0].fs.retries == 5  # a zarr open that writes: a writer's
    assert write.zarr_args("r")[0].fs.retries == 5
    back = pickle.loads(pickle.dumps(rfs))
    assert type(back) is ReadS3FileSystem and back.retries == 2
    # the control: a plain s3fs filesystem keeps its class's 5
    assert s3fs.S3FileSystem(anon=True).retries == 5
    # other URLs are handed to zarr as before
    assert Location("https://h/x.zarr").zarr_args("r")[0] == "https://h/x.zarr"
