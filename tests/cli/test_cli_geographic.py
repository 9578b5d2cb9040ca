"""A geographic store (x/y in degrees) tiles losslessly but every streaming and rendering command
refuses it with the command to run; ``-q`` does not hide the message (issue 13 item 2)."""

from __future__ import annotations

import pytest
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
COMMANDS = ["stream", "render", "tradeoff", "flythrough", "view", "compare"]


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("geo")
    src = write_dem(
        d / "geo.tif", fractal((121, 121), 3), crs="EPSG:4326", origin=(-72.0, 45.0), cell=1 / 1200
    )
    geo, utm = d / "geo.zarr", d / "utm.zarr"
    for dst, extra in ((geo, []), (utm, ["--dst-crs", "auto"])):
        r = runner.invoke(app, ["tile", str(src), str(dst), "--block-size", "65", *extra])
        assert r.exit_code == 0, r.output
    return geo, utm


@pytest.mark.parametrize("command", COMMANDS)
def test_every_viewing_command_refuses_a_geographic_store(stores, command, tmp_path):
    geo, _ = stores
    r = runner.invoke(app, ["-q", command, str(geo)])
    assert r.exit_code == 2, r.output
    assert "geographic CRS" in r.output and "--dst-crs auto" in r.output


def test_the_python_api_refuses_it_too(stores):
    from streamer.session import open_session
    from tiler.errors import GeographicStoreError

    geo, utm = stores
    with pytest.raises(GeographicStoreError, match="degrees"):
        open_session(str(geo))
    with open_session(str(utm)) as s:  # the quiet case: the reprojected store streams
        assert s.store.meta.crs_wkt and "UTM" in s.store.meta.crs_wkt


def test_info_says_where_the_crs_came_from(stores):
    geo, utm = stores
    r = runner.invoke(app, ["info", str(geo)])
    assert r.exit_code == 0 and "geographic: tiles losslessly" in r.output
    r = runner.invoke(app, ["info", str(utm)])
    assert r.exit_code == 0 and "EPSG:32619 (reprojected from EPSG:4326, auto" in r.output
