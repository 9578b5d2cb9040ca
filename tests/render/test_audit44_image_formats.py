"""Image outputs whose extension's format cannot hold the picture: ``render -o v.ico --size
300x200`` wrote a 128x85 icon and ``-o v.pbm`` a colour P6 pixmap under a bitmap's name, both
with exit 0 ("wrote v.ico"); ``-o v.xbm`` drew the view, then failed with Pillow's OSError
(exit 1). Now each is a usage error naming --out (before anything is drawn where the format
cannot hold any RGB picture). Controls: .png (read back pixel for pixel), .jpg, .tif, .ppm."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem
from PIL import Image
from typer.testing import CliRunner

from cli.main import app
from render.flythrough import ImageFormatError, encode_image

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()
PICTURE = np.random.default_rng(3).integers(0, 256, (48, 64, 3), dtype=np.uint8)


@pytest.mark.parametrize(
    ("name", "said"),
    [
        ("v.xbm", "cannot write the picture as XBM"),
        ("v.palm", "cannot write the picture as PALM"),
        ("v.pbm", "a .pbm file is a Netpbm bitmap"),
        ("v.pfm", "a .pfm file is a Netpbm float map"),
        ("v.icns", "cannot hold a 64x48 picture: it would be 1024x1024"),
        ("v", "from its extension '(none)'"),
    ],
)
def test_formats_that_cannot_hold_the_picture_are_refused(name, said):
    with pytest.raises(ImageFormatError, match=said.replace("(", r"\(").replace(")", r"\)")):
        encode_image(PICTURE, name)


def test_an_icon_larger_than_256_is_refused_not_shrunk():
    big = np.zeros((200, 300, 3), np.uint8)
    with pytest.raises(ImageFormatError, match=r"cannot hold a 300x200 picture: it would be"):
        encode_image(big, "v.ico")
    assert encode_image(PICTURE[:32, :32], "v.ico")  # (an icon's size: kept)


@pytest.mark.parametrize("name", ["v.png", "v.PNG", "v.tif", "v.ppm", "v.bmp"])
def test_lossless_formats_keep_the_picture(name):
    data = encode_image(PICTURE, name)
    with Image.open(io.BytesIO(data)) as im:
        assert np.array_equal(np.asarray(im.convert("RGB")), PICTURE)
    assert encode_image(PICTURE, "v.jpg")[:2] == b"\xff\xd8"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return str(tile_dem(tmp_path_factory.mktemp("img44"), rough(65, 7), 33))


@pytest.mark.gl
def test_render_refuses_an_unwritable_format_before_drawing(store, tmp_path, monkeypatch):
    make_context()
    import render.pipeline

    def no_drawing(*a, **k):
        raise AssertionError("drew a view for a file it cannot write")

    monkeypatch.setattr(render.pipeline, "render_view", no_drawing)
    for name, said in [("v.xbm", "XBM"), ("v.pbm", "Netpbm bitmap"), ("v.icns", "keep")]:
        res = runner.invoke(app, ["render", store, "--size", "64x48", "-o", str(tmp_path / name)])
        assert res.exit_code == 2, res.output
        assert "--out" in res.output and said in res.output, res.output
        assert not (tmp_path / name).exists()


@pytest.mark.gl
def test_render_refuses_an_icon_of_the_wrong_size_and_writes_a_png(store, tmp_path):
    make_context()
    ico = tmp_path / "v.ico"
    res = runner.invoke(app, ["render", store, "--size", "300x200", "-o", str(ico)])
    assert res.exit_code == 2 and "cannot hold a 300x200 picture" in res.output, res.output
    assert not ico.exists() and not list(tmp_path.glob("*.partial"))
    for name in ("v.png", "v.ppm", "v.jpg"):  # controls
        out = tmp_path / name
        res = runner.invoke(app, ["render", store, "--size", "300x200", "-o", str(out)])
        assert res.exit_code == 0, res.output
        with Image.open(out) as im:
            assert im.size == (300, 200)


def test_view_refuses_an_unwritable_screenshot_before_opening_a_window(store, tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    cmd = [sys.executable, "-c", "from cli.main import main; main()", "view", store,
           "--frames", "1", "--screenshot", str(tmp_path / "s.xbm")]  # fmt: skip
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert "--screenshot" in res.stderr and "XBM" in res.stderr, res.stderr
    # control: a .png screenshot passes this check (and stops at the missing display)
    cmd[-1] = str(tmp_path / "s.png")
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert "needs a display" in res.stderr and "XBM" not in res.stderr, res.stderr
