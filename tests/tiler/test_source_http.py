"""Sources behind a URL: a server that fails, refuses or stops answering is reported as the
server's failure, in bounded time, never as a file GDAL does not recognise nor as a hang
(:mod:`tiler.source_http`). Each detector has its control: the server left unasked (GDAL's own
message comes back), and GDAL left at its defaults (the open or the read hangs until the test
lets the server go). The server runs in a child process: GDAL holds the GIL through some of its
requests (the header's side files), which an in-process server could never answer."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import ServerProcess
from typer.testing import CliRunner

import tiler.source_header
from cli.main import app
from tiler import source_http
from tiler.errors import SourceError, SourceNotFoundError, SourceUnavailableError
from tiler.mosaic import MosaicReader, plan_mosaic
from tiler.source_header import open_raster
from tiler.source_http import (
    GDAL_HTTP_DEFAULTS,
    gdal_http_options,
    http_url,
    is_remote,
    probe_timeout,
    remote_env,
    server_failure,
)
from tiler.store import open_store

runner = CliRunner()
QUICK_S = 1  # the tests' "seconds without a byte" (the default is 30)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A folder holding ``d.tif``, 1025² int16 in strips (2 MB: windows far apart are separate
    requests), and the samples."""
    d = tmp_path_factory.mktemp("source_http")
    data = fractal((1025, 1025), 3)
    write_dem(d / "d.tif", data, cell=10.0)
    return d, data


@pytest.fixture
def quick(monkeypatch):
    """GDAL's and the probe's limits at :data:`QUICK_S` and its retries 0.1 s apart, none set
    by the environment."""
    for k in GDAL_HTTP_DEFAULTS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setitem(GDAL_HTTP_DEFAULTS, "GDAL_HTTP_LOW_SPEED_TIME", str(QUICK_S))
    monkeypatch.setitem(GDAL_HTTP_DEFAULTS, "GDAL_HTTP_CONNECTTIMEOUT", str(QUICK_S))
    monkeypatch.setitem(GDAL_HTTP_DEFAULTS, "GDAL_HTTP_RETRY_DELAY", "0.1")  # (still 2 retries)
    monkeypatch.setattr(source_http, "PROBE_TIMEOUT_S", float(QUICK_S))


#: the controls' child: GDAL at its defaults (``remote_env`` does nothing), the open, the
#: server stalled (the parent is told "stall?" and answers), then a far window read
CONTROL = textwrap.dedent(
    """
    import contextlib, sys
    for k in list(__import__("os").environ):
        if k.startswith("GDAL_HTTP_"):
            del __import__("os").environ[k]
    import tiler.mosaic, tiler.source_header
    from tiler.mosaic import MosaicReader, plan_mosaic
    off = lambda *p: contextlib.nullcontext()
    tiler.source_header.remote_env = tiler.mosaic.remote_env = off
    url, when = sys.argv[1], sys.argv[2]
    if when == "open":
        print("stall?", flush=True); sys.stdin.readline()
    reader = MosaicReader(plan_mosaic([url], band=1))
    reader.read_window(0, 0, 8, 8)
    if when == "read":
        print("stall?", flush=True); sys.stdin.readline()
    reader.read_window(1000, 0, 25, 1025)
    print("ended", flush=True)
    """
)


def _control(served, when: str) -> None:
    """GDAL at its defaults waits for a stalled server (``when``: at the ``open`` or a
    ``read``) until the server lets go: the child is still running after 6 s."""
    d, _ = served
    with ServerProcess(d) as srv:
        child = subprocess.Popen(
            [sys.executable, "-c", CONTROL, f"{srv.url}/d.tif", when],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert child.stdout.readline().strip() == "stall?"
            srv.send("stall")
            child.stdin.write("go\n")
            child.stdin.flush()
            with pytest.raises(subprocess.TimeoutExpired):
                child.wait(6 * QUICK_S)  # hung: the detector's limits are what end it
            srv.send("release")  # the stalled requests end unanswered
            child.wait(60)
        finally:
            child.kill()
            child.communicate(timeout=30)  # (reaped, its pipes closed)


# -- pure ---------------------------------------------------------------------------------


def test_remote_paths_and_the_options_the_environment_leaves():
    for p in ("http://h/d.tif", "https://h/d.tif", "s3://b/d.tif", "/vsicurl/http://h/d.tif",
              "/vsizip//vsis3/b/a.zip/n44.hgt", "/vsigs/b/d.tif"):  # fmt: skip
        assert is_remote(p), p
    for p in ("d.tif", "/data/d.tif", "/vsizip/a.zip/n44.hgt", "/vsimem/d.tif"):
        assert not is_remote(p), p
    assert gdal_http_options({}) == GDAL_HTTP_DEFAULTS
    own = gdal_http_options({"GDAL_HTTP_LOW_SPEED_TIME": "120", "GDAL_HTTP_MAX_RETRY": "0"})
    assert "GDAL_HTTP_LOW_SPEED_TIME" not in own and "GDAL_HTTP_MAX_RETRY" not in own
    assert own["GDAL_HTTP_CONNECTTIMEOUT"] == "30"
    assert http_url("/vsicurl/https://h/d.tif") == "https://h/d.tif"
    assert http_url("s3://b/d.tif") is None and http_url("d.tif") is None
    assert probe_timeout({}) == source_http.PROBE_TIMEOUT_S
    assert probe_timeout({"GDAL_HTTP_LOW_SPEED_TIME": "2"}) == 2.0
    assert probe_timeout({"GDAL_HTTP_LOW_SPEED_TIME": "600"}) == source_http.PROBE_TIMEOUT_S
    assert probe_timeout({"GDAL_HTTP_LOW_SPEED_TIME": "soon"}) == source_http.PROBE_TIMEOUT_S


# -- the probe ----------------------------------------------------------------------------


def test_the_probe_tells_a_failing_server_from_a_serving_one(served):
    d, _ = served
    with ServerProcess(d) as srv:
        url = srv.url
        assert server_failure(f"{url}/d.tif", 2) is None  # serves: the control
        assert server_failure(f"{url}/gone.tif", 2)[1] == 404
        srv.send("status 503")
        what, status = server_failure(f"{url}/d.tif", 2)
        assert status == 503 and "HTTP 503" in what
        srv.send("status -")
        srv.send("stall")
        t0 = time.monotonic()
        what, status = server_failure(f"{url}/d.tif", 0.5)
        assert status is None and what == "did not answer in 0.5 s"
        assert time.monotonic() - t0 < 5
        srv.send("release")
    what, status = server_failure(url + "/d.tif", 2)  # the server is gone now
    assert status is None and what.startswith("cannot be reached")


@pytest.mark.parametrize(
    ("status", "error", "words"),
    [
        (503, SourceUnavailableError, "answers HTTP 503"),
        (403, SourceUnavailableError, "access was refused"),
        (404, SourceNotFoundError, "does not exist: its server answers HTTP 404"),
    ],
)
def test_opening_over_a_failing_server_names_the_server(served, quick, status, error, words):
    d, _ = served
    with ServerProcess(d) as srv:
        srv.send(f"status {status}")
        with pytest.raises(error, match=words) as info:
            open_raster(f"{srv.url}/d.tif")
        assert f"{srv.url}/d.tif" in str(info.value)
        assert "GDAL_HTTP_LOW_SPEED_TIME" not in str(info.value)  # (not a matter of time)


def test_control_unasked_the_server_failure_reads_as_an_unrecognised_file(
    served, quick, monkeypatch
):
    d, _ = served
    monkeypatch.setattr(tiler.source_header, "server_failure", lambda *a, **k: None)
    with ServerProcess(d) as srv:
        srv.send("status 503")
        with pytest.raises(SourceError, match="not recognized") as info:
            open_raster(f"{srv.url}/d.tif")
    assert not isinstance(info.value, SourceUnavailableError)


def test_opening_over_a_stalled_server_gives_up(served, quick):
    d, _ = served
    with ServerProcess(d) as srv:
        srv.send("stall")
        t0 = time.monotonic()
        with pytest.raises(SourceUnavailableError, match=f"did not answer in {QUICK_S} s") as e:
            open_raster(f"{srv.url}/d.tif")
        assert time.monotonic() - t0 < 20  # GDAL's requests (~1 s each) and the probe's
        assert "GDAL_HTTP_LOW_SPEED_TIME sets the seconds" in str(e.value)
        srv.send("release")


def test_control_at_gdals_defaults_the_open_waits_for_the_server(served):
    _control(served, "open")


def test_a_read_after_the_server_stops_answering_fails_naming_it(served, quick):
    d, data = served
    with ServerProcess(d) as srv:
        with MosaicReader(plan_mosaic([f"{srv.url}/d.tif"], band=1)) as reader:
            np.testing.assert_array_equal(reader.read_window(0, 0, 8, 8), data[:8, :8])
            srv.send("stall")
            t0 = time.monotonic()
            with pytest.raises(SourceUnavailableError) as info:
                reader.read_window(1000, 0, 25, 1025)
            assert time.monotonic() - t0 < 20
        srv.send("release")
    assert "rows 1000..1024" in str(info.value)
    assert "rerun the same command to resume" in str(info.value)


def test_control_a_read_at_gdals_defaults_waits_for_the_server(served):
    _control(served, "read")


def test_tile_from_a_failing_server_exits_1_naming_it(served, quick, tmp_path):
    d, _ = served
    with ServerProcess(d) as srv:
        srv.send("status 503")
        r = runner.invoke(app, ["tile", f"{srv.url}/d.tif", str(tmp_path / "s.zarr")])
    assert r.exit_code == 1, r.output
    assert "answers HTTP 503" in r.output and "not the file" in r.output
    assert not (tmp_path / "s.zarr").exists()  # refused before anything was written


def test_tile_from_a_served_url(served, quick, tmp_path):
    d, data = served
    with ServerProcess(d) as srv:
        r = runner.invoke(app, ["tile", f"{srv.url}/d.tif", str(tmp_path / "s.zarr"),
                                "--block-size", "257", "--workers", "1"])  # fmt: skip
    assert r.exit_code == 0, r.output
    block = open_store(tmp_path / "s.zarr").read_block((1, 2))
    np.testing.assert_array_equal(block, data[256:513, 512:769])


def test_the_callers_own_gdal_settings_win():
    import rasterio
    import rasterio.env

    with remote_env("https://h/d.tif"):  # the control: the defaults apply
        assert rasterio.env.getenv()["GDAL_HTTP_LOW_SPEED_TIME"] == "30"
    with rasterio.Env(GDAL_HTTP_LOW_SPEED_TIME="120"), remote_env("https://h/d.tif"):
        opts = rasterio.env.getenv()
        assert opts["GDAL_HTTP_LOW_SPEED_TIME"] == "120"  # the caller's
        assert opts["GDAL_HTTP_CONNECTTIMEOUT"] == "30"  # the rest still set
    with remote_env("dem.tif"):  # a local file: nothing set
        assert not rasterio.env.hasenv() or "GDAL_HTTP_LOW_SPEED_TIME" not in rasterio.env.getenv()
