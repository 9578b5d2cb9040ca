"""``--nodata-rule`` reaches qiu's strategy and its streaming session (render, tradeoff); a
strategy that does not take the rule is a usage error naming it and the strategies that do."""

from __future__ import annotations

import json

import numpy as np
import pytest
from demtools import write_dem
from typer.testing import CliRunner

from cli.main import app
from cli.options import NODATA_DEFAULT, NODATA_RULES

runner = CliRunner()
COMMANDS = ["render", "view", "tradeoff", "flythrough", "compare"]


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def checkerboard(tmp_path_factory):
    """A 257² DEM (30 m cells, blocks of 65²) whose 64-sample squares alternate between terrain
    and nodata, and a camera straight down from 40 km over its centre (``--camera`` value)."""
    from tiler.store import open_store

    n = 257
    r, c = np.mgrid[0:n, 0:n]
    dem = 800 + 40 * np.sin(c / 9.0) * np.cos(r / 7.0) + 0.2 * ((r * 7 + c * 13) % 17)
    valid = ((r + 32) // 64 + (c + 32) // 64) % 2 == 1
    d = tmp_path_factory.mktemp("cb")
    src = write_dem(d / "dem.tif", np.where(valid, np.rint(dem), -9999).astype(np.int16),
                    nodata=-9999)  # fmt: skip
    res = run("tile", src, d / "s.zarr", "--block-size", "65")
    assert res.exit_code == 0, res.output
    x0, y0, x1, y1 = open_store(str(d / "s.zarr")).grid.extent
    return str(d / "s.zarr"), f"{(x0 + x1) / 2},{(y0 + y1) / 2},40800"


VIEW = ["--pitch", "-90", "--size", "128x128", "--patch-log2", "2"]


def test_the_default_is_the_first_rule():
    assert NODATA_DEFAULT == NODATA_RULES.names[0] == "full" and "gap" in NODATA_RULES.names


@pytest.mark.gl
def test_render_gap_draws_fewer_triangles_and_says_so(checkerboard, tmp_path, gl_context):
    store, cam = checkerboard
    out = {}
    for rule in ("full", "gap"):
        res = run("render", store, "--camera", cam, *VIEW, "--tau", "1", "--nodata-rule", rule,
                  "-o", tmp_path / f"{rule}.png", "--json")  # fmt: skip
        assert res.exit_code == 0, res.output
        out[rule] = json.loads(res.stdout)
    assert out["full"]["nodata_rule"] == "full" and out["gap"]["nodata_rule"] == "gap"
    assert 0 < out["gap"]["triangles"] < out["full"]["triangles"] / 3, out
    assert out["gap"]["clamped"] == 0 and out["full"]["clamped"] == 0


@pytest.mark.gl
def test_tradeoff_gap_loads_fewer_bytes(checkerboard, tmp_path, gl_context):
    """The rule reaches the session too: loaded bytes fall, no node is clamped."""
    store, cam = checkerboard
    rows = {}
    for rule in ("full", "gap"):
        js = tmp_path / f"{rule}.json"
        res = run("tradeoff", store, "--camera", cam, *VIEW, "--taus", "1", "--repeats", "1",
                  "--nodata-rule", rule, "--json", js)  # fmt: skip
        assert res.exit_code == 0, res.output
        (rows[rule],) = json.loads(js.read_text())
    full, gap = rows["full"], rows["gap"]
    assert full["nodata"] == "full" and gap["nodata"] == "gap"
    assert gap["loaded_bytes"] < full["loaded_bytes"] and gap["triangles"] < full["triangles"]
    assert gap["clamped"] == 0 and full["clamped"] == 0
    assert gap["uncovered_px"] <= 1.0 and gap["nodata_covered"] == 0.0


@pytest.mark.parametrize("command", COMMANDS)
def test_a_strategy_without_the_rule_exits_2_naming_it(checkerboard, command, tmp_path):
    store, _ = checkerboard
    lod = ["--lods", "qiu,jung-han"] if command == "compare" else ["--lod", "jung-han"]
    out = ["--out", tmp_path / "o"] if command == "flythrough" else []
    res = run(command, store, *lod, "--nodata-rule", "gap", *out)
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())
    assert "--nodata-rule" in text and "'jung-han' does not take the nodata rule 'gap'" in text
    assert "the strategies that do: qiu" in text
    assert not (tmp_path / "o").exists()


def test_compare_of_every_strategy_with_gap_exits_2(checkerboard):
    res = run("compare", checkerboard[0], "--nodata-rule", "gap", "--quick")
    assert res.exit_code == 2 and "the strategies that do: qiu" in " ".join(res.output.split())


def test_an_unknown_rule_exits_2_listing_the_rules(checkerboard):
    res = run("render", checkerboard[0], "--nodata-rule", "nope")
    assert res.exit_code == 2
    assert "unknown nodata rule 'nope'; choose one of full, gap" in " ".join(res.output.split())
