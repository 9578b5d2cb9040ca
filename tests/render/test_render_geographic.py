"""A geographic DEM tiled with dst_crs="auto" renders terrain like a projected store does."""

from __future__ import annotations

import re

import numpy as np
import pytest
from demtools import shared_file
from gltools import make_context
from PIL import Image
from typer.testing import CliRunner

from cli.main import app
from tiler.crs import crs_name
from tiler.tile import TileOptions, tile

pytestmark = [pytest.mark.gl, pytest.mark.shared_data]
make_context()


def render(store: str, out) -> tuple[int, np.ndarray]:
    res = CliRunner().invoke(app, ["render", store, "--size", "160x120", "-o", str(out)])
    assert res.exit_code == 0, res.output
    triangles = int(re.search(r"([\d,]+) triangles", res.output).group(1).replace(",", ""))
    return triangles, np.asarray(Image.open(out).convert("RGB"), dtype=np.float64)


def terrain_pixels(img: np.ndarray) -> np.ndarray:
    sky = img[0, 0]
    return img[np.abs(img - sky).sum(axis=-1) > 30]


def test_auto_crs_store_renders_terrain_near_a_projected_one(tmp_path):
    src = shared_file("N44W072.hgt")
    auto = tile(src, tmp_path / "auto.zarr", TileOptions(block_size=257, dst_crs="auto"))
    assert crs_name(auto.meta.crs_wkt) == "EPSG:32619"
    other = TileOptions(block_size=257, dst_crs="EPSG:32618")  # projected, neighbouring zone
    ref = tile(src, tmp_path / "z18.zarr", other)
    n_auto, img_auto = render(auto.url, tmp_path / "auto.png")
    n_ref, _ = render(ref.url, tmp_path / "z18.png")
    assert 0.75 * n_ref <= n_auto <= 1.25 * n_ref, (n_auto, n_ref)
    ground = terrain_pixels(img_auto)
    assert ground.shape[0] > 0.1 * img_auto.shape[0] * img_auto.shape[1]  # terrain in view
    assert ground.std(axis=0).max() > 10  # shaded relief, not a flat colour
