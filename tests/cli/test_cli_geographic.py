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


# --- x/y in feet: the same refusal, since drawn they would be stretched 3.28x across ----------


@pytest.fixture(scope="module")
def feet_stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("feet")
    src = write_dem(
        d / "ft.tif", fractal((121, 121), 4), crs="EPSG:2263", origin=(1e6, 2e5), cell=30.0
    )
    ft, m, comp = d / "ft.zarr", d / "m.zarr", d / "comp.zarr"
    for dst, extra in ((ft, []), (m, ["--dst-crs", "auto"])):
        r = runner.invoke(app, ["tile", str(src), str(dst), "--block-size", "65", *extra])
        assert r.exit_code == 0, r.output
        warned = "in US survey foot while heights are metres" in r.output
        assert warned == (not extra), r.output  # said while tiling, not for the metre store
    compound = write_dem(d / "comp.tif", fractal((121, 121), 4), crs="EPSG:32619+5703")
    r = runner.invoke(app, ["tile", str(compound), str(comp), "--block-size", "65"])
    assert r.exit_code == 0, r.output
    return ft, m, comp


@pytest.mark.parametrize("command", COMMANDS)
def test_every_viewing_command_refuses_a_store_in_feet(feet_stores, command):
    ft, _, _ = feet_stores
    r = runner.invoke(app, ["-q", command, str(ft)])
    assert r.exit_code == 2, r.output
    assert "US survey foot" in r.output and "stretched 3.28x" in r.output, r.output
    assert "--dst-crs auto" in r.output


def test_a_store_in_feet_is_refused_by_the_api_and_named_by_info(feet_stores):
    from streamer.session import open_session
    from tiler.crs import parse_dst_crs
    from tiler.errors import GeographicStoreError, SourceError

    ft, m, comp = feet_stores
    with pytest.raises(GeographicStoreError, match="US survey foot"):
        open_session(str(ft))
    for ok in (m, comp):  # the controls: reprojected to UTM, and a compound CRS in metres
        with open_session(str(ok)) as s:
            assert s.store.meta.crs_wkt
    r = runner.invoke(app, ["info", str(ft)])
    assert r.exit_code == 0 and "EPSG:2263 (x/y in US survey foot" in r.output, r.output
    r = runner.invoke(app, ["info", str(comp)])
    assert r.exit_code == 0 and "x/y in" not in r.output, r.output
    with pytest.raises(SourceError, match="x/y in US survey foot"):
        parse_dst_crs("EPSG:2263")
    assert parse_dst_crs("EPSG:32619+5703")  # a compound target in metres is fine
