"""Every command that reads a store takes ``--storage-options``: the advice of a timed-out read
("raise the storage option 'timeout'") was not something ``tradeoff``, ``compare``,
``flythrough``, ``view`` or ``verify`` could follow, and an S3 endpoint or key could only come
from the environment. The option reaches the store: for a local path it is refused naming it
(each command), and over a stalled server its ``timeout`` ends ``verify`` in seconds where the
default waits 30 s per read."""

from __future__ import annotations

import time

import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
READERS = ["info", "export", "stream", "render", "tradeoff", "flythrough", "view", "compare",
           "verify"]  # fmt: skip


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from tiler.tile import TileOptions, tile

    d = tmp_path_factory.mktemp("so")
    src = write_dem(d / "dem.tif", fractal((65, 65), 4))
    tile(src, d / "s.zarr", TileOptions(block_size=33, workers=1))
    return d / "s.zarr"


@pytest.mark.parametrize("command", READERS)
def test_every_store_reader_takes_storage_options(store, tmp_path, command):
    extra = [tmp_path / "out.tif"] if command == "export" else []
    r = run(command, store, *extra, "--storage-options", '{"timeout": 1}')
    assert r.exit_code == 2, r.output
    assert "--storage-options" in r.output and "not to" in r.output  # reached the store
    assert "No such option" not in r.output


def test_the_timeout_reaches_verify_over_a_stalled_server(store):
    srv = LoopbackServer(store.parent)
    with srv as url:
        r = run("verify", f"{url}/{store.name}", "--storage-options", '{"timeout": 1}')
        assert r.exit_code == 0, r.output  # the control: the server answers
        srv.stall.set()
        t0 = time.monotonic()
        r = run("verify", f"{url}/{store.name}", "--storage-options", '{"timeout": 1}')
        took = time.monotonic() - t0
    assert r.exit_code == 1, r.output
    assert "did not answer in time" in r.output and "nothing was concluded" in r.output
    assert took < 20  # the default (30 s per read) would not have answered yet
