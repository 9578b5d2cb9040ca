"""``--lod`` and ``terrastream compare`` through Typer's CliRunner."""

from __future__ import annotations

import json

import pytest
from gltools import make_context, rough, tile_dem
from typer.testing import CliRunner

from cli.main import app
from render.strategies import strategy_names

pytestmark = pytest.mark.gl
make_context()
runner = CliRunner()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return str(tile_dem(tmp_path_factory.mktemp("cli"), rough(65, 7), 33))


def test_unknown_lod_exits_2_listing_the_choices(store, tmp_path):
    res = runner.invoke(app, ["render", store, "--size", "96x64", "--lod", "nope"])
    assert res.exit_code == 2
    assert "unknown LOD strategy 'nope'" in res.output and "chunk-tessellation" in res.output


def test_render_with_chunk_tessellation(store, tmp_path):
    out = tmp_path / "v.png"
    res = runner.invoke(
        app, ["render", store, "--size", "96x64", "--lod", "chunk-tessellation", "-o", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert out.stat().st_size > 0 and "triangles" in res.output


def test_compare_writes_rows_per_strategy_and_tau(store, tmp_path):
    js = tmp_path / "c.json"
    res = runner.invoke(
        app,
        ["compare", store, "--size", "96x64", "--frames", "2", "--taus", "1,4",
         "--patch-log2", "2", "--json", str(js)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    rows = json.loads(js.read_text())
    assert {(r["strategy"], r["tau"]) for r in rows} == {
        (s, t) for s in strategy_names() for t in (1.0, 4.0)
    }
    for r in rows:
        assert r["crack_pixels"] == 0 and r["popping_px"] >= 0 and r["triangles"] > 0
        assert r["used_bytes"] > 0 and r["popping_steps"] == 8
