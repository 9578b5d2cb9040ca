"""Extreme default views (audit 44b): the cause of "no terrain pixel", and an overview that
frames a DEM whose relief dwarfs its extent.

Before: ``render S --size 1x2`` and the overview of a DEM 0.64 m wide with 500 m of relief
both failed with "the DEM is too far from the camera to be seen". The 1x2 view is too small to
hold a terrain pixel (the DEM's image falls between its two pixel centres); the steep DEM was
framed as a 500 m tall box seen from 35° above, a sliver 0.15 px wide. The overview now looks
down more steeply on such a DEM (``render.views.STEEP_RATIO``) and the message names the cause
(``render.views.no_pixel_cause``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem
from typer.testing import CliRunner

from cli.main import app
from render.views import STEEP_RATIO, overview_camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
make_context()
runner = CliRunner()


def _ramp(tmp, relief: float, cell: float = 0.01, n: int = 65) -> str:
    z = (np.linspace(0.0, relief, n)[None, :] * np.ones((n, 1))).astype(np.float32)
    return str(tile_dem(tmp, z, 65, cell=cell))


@pytest.fixture(scope="module")
def steep(tmp_path_factory):
    """65 x 65 samples 0.01 m apart (0.64 m wide) rising 0 .. 500 m west to east."""
    return _ramp(tmp_path_factory.mktemp("steep"), 500.0)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    return str(tile_dem(tmp_path_factory.mktemp("plain"), rough(65, 7), 33))


def _render(store, tmp_path, *args):
    out = tmp_path / "v.png"
    res = runner.invoke(app, ["render", store, "-o", str(out), "--overwrite", "--json", *args])
    return res, out


def test_the_overview_of_a_steep_dem_draws_it(steep, tmp_path):
    """Before: exit 2, "too far from the camera". Now the overview looks (nearly) straight
    down on it and draws it."""
    res, out = _render(steep, tmp_path, "--size", "128x96")
    assert res.exit_code == 0, res.output
    assert json.loads(res.output.splitlines()[-1])["drawn_px"] > 100 and out.exists()
    cam = overview_camera(open_store(steep), (128, 96))
    assert cam.pitch < -80.0


def test_quiet_the_overview_of_a_usual_dem_is_unchanged(plain, tmp_path):
    """Quiet case: a DEM whose relief is within STEEP_RATIO / cos 35° of its extent keeps the
    35° overview (the same camera as before), even just below that bound; so does one whose
    relief is 10 times its extent (1.92 km wide, -11,000 .. 8,848 m) but whose footprint the
    35° framing still shows over STEEP_MIN_PX pixels (it draws terrain from there)."""
    assert overview_camera(open_store(plain), (128, 96)).pitch == pytest.approx(-35.0)
    side = 0.64
    below = 0.99 * STEEP_RATIO * side / np.cos(np.radians(35.0))
    (tmp_path / "below").mkdir()
    s = open_store(_ramp(tmp_path / "below", below))
    assert overview_camera(s, (128, 96)).pitch == pytest.approx(-35.0)
    (tmp_path / "ocean").mkdir()
    z = np.linspace(-11000.0, 8848.0, 65 * 65, dtype=np.float32).reshape(65, 65)
    s = open_store(tile_dem(tmp_path / "ocean", z, 65, cell=30.0))
    assert (s.index.zmax.max() - s.index.zmin.min()) * np.cos(np.radians(35)) > 2 * 1920
    assert overview_camera(s, (128, 96)).pitch == pytest.approx(-35.0)


def test_an_edge_on_view_of_a_steep_dem_names_its_relief(steep, tmp_path):
    """A camera of the user's, south of the steep DEM at mid-height looking north: the ramp is
    seen edge-on, a sliver narrower than a pixel. The message names relief and extent, not
    distance."""
    cam = ["--camera", "500000.32,4999000,250", "--look-at", "500000.32,4999999.7,250"]
    res, out = _render(steep, tmp_path, "--size", "128x96", *cam)
    assert res.exit_code == 2, res.output
    assert "500 m relief" in res.output and "sliver" in res.output, res.output
    assert "too far" not in res.output and not out.exists()


def test_a_view_too_small_for_a_pixel_says_so(plain, tmp_path):
    """``--size 1x2``: the DEM's image lies between the two pixel centres. Before: "the DEM is
    too far from the camera"; now the size is named. Quiet case: 1x1 and 2x2 draw."""
    res, out = _render(plain, tmp_path, "--size", "1x2")
    assert res.exit_code == 2, res.output
    assert "--size" in res.output and "too small to hold a terrain pixel" in res.output
    assert "too far" not in res.output and not out.exists()
    for size in ("1x1", "2x2"):
        res, _ = _render(plain, tmp_path, "--size", size)
        assert res.exit_code == 0, res.output


def test_a_dem_far_below_a_pixel_is_still_called_too_far(plain, tmp_path):
    """Positive control of the distance cause: from 10,000 km straight above the DEM's image
    is far below a pixel."""
    x0, y0, x1, y1 = open_store(plain).grid.extent
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    cam = ["--camera", f"{cx},{cy},1e7", "--look-at", f"{cx},{cy + 1},0"]
    res, _ = _render(plain, tmp_path, "--size", "96x64", *cam)
    assert res.exit_code == 2, res.output
    assert "smaller than a pixel" in res.output and "too far from the camera" in res.output
