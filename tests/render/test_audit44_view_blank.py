"""`view --frames N --screenshot F` whose last frame drew no terrain (the camera looking at the
sky) wrote a picture of sky and exited 0 ("wrote F"); `render` of the same camera exits 2.
Now a usage error naming --camera, the screenshot not kept. The control: the default view
writes its screenshot, exit 0."""

from __future__ import annotations

from pathlib import Path

import pytest
import test_viewer as tv
from gltools import rough, tile_dem

display = tv.display  # an X display: the viewer tests' own Xvfb, else $DISPLAY, else skip


@pytest.fixture(scope="module")
def store_path(tmp_path_factory) -> Path:
    pytest.importorskip("glfw", reason="the viewer's window library is missing: pip install glfw")
    return tile_dem(tmp_path_factory.mktemp("viewblank"), rough(65, 7), 33)


@pytest.mark.gl
def test_a_screenshot_of_sky_is_an_error_not_a_view(store_path, display, tmp_path):
    from tiler.store import open_store

    x0, y0, x1, y1 = open_store(store_path).grid.extent
    cam = f"{0.5 * (x0 + x1)},{0.5 * (y0 + y1)},3000"
    shot = tmp_path / "sky.png"
    res = tv._view(store_path, display, "--size", "96x64", "--frames", "2", "--workers", "1",
                   "--camera", cam, "--pitch", "60", "--screenshot", str(shot))  # fmt: skip
    tv._skip_without_gl_window(res)
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "drew no terrain pixel (0 triangles)" in res.stderr and "--camera" in res.stderr
    assert "the camera sees none of the DEM" in res.stderr and "wrote" not in res.stdout
    assert "the screenshot was not kept" in res.stderr and "streaming said" not in res.stderr
    assert not shot.exists()
    # control: looking down at the DEM (the default view) keeps its screenshot
    ok = tmp_path / "ok.png"
    res = tv._view(store_path, display, "--size", "96x64", "--frames", "2", "--workers", "1",
                   "--screenshot", str(ok))  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert ok.exists() and f"wrote {ok}" in res.stdout
