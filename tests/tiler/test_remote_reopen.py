"""A remote source whose server cannot be reached is "unavailable" every time it is opened,
not only the first: GDAL's network file systems remember a path they could not reach as
absent for the rest of the process, so a retry in the same process (a notebook, a service)
said "'/vsis3/...' does not exist in the file system" (a usage error, exit 2) while the
server was still down. The control: with GDAL's memory left alone, the retry is misnamed
(the test's scene does reproduce it)."""

from __future__ import annotations

import socket

import pytest

import tiler.source_header as sh
from tiler.errors import SourceError, SourceUnavailableError
from tiler.source_http import forget_failed_open


@pytest.fixture
def dead_endpoint(monkeypatch):
    """AWS settings pointing at a loopback port nothing listens on."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    for k, v in {
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
        "GDAL_HTTP_MAX_RETRY": "0",
    }.items():
        monkeypatch.setenv(k, v)
    return port


def test_a_second_open_of_an_unreachable_s3_source_is_still_unavailable(dead_endpoint):
    path = f"s3://reopen-{dead_endpoint}/dem.tif"
    for _ in range(3):
        with pytest.raises(SourceUnavailableError, match="could not get it from its server"):
            sh.open_raster(path)


def test_the_control_without_forgetting_the_retry_is_misnamed(dead_endpoint, monkeypatch):
    assert forget_failed_open()  # (found in rasterio's GDAL; else the fix cannot work)
    monkeypatch.setattr(sh, "forget_failed_open", lambda: False)
    path = f"s3://reopen-control-{dead_endpoint}/dem.tif"
    with pytest.raises(SourceUnavailableError):
        sh.open_raster(path)
    with pytest.raises(SourceError, match="does not exist in the file system") as e:
        sh.open_raster(path)
    assert not isinstance(e.value, SourceUnavailableError)
    forget_failed_open()  # (leave no remembered path to the tests after this one)
