"""``conservative-view`` on the GPU: measured max screen error <= tau with Qiu's strategy at
FOV 5-170 degrees (issue 12 item 5), with each node's box (its own height range); positive
controls: a quarter of the bound is exceeded, with spheres and with boxes."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render import measure
from render.pipeline import heights_fn
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies.qiu import patch_counts
from streamer.camera import Camera
from streamer.lod import conservative_view
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
FOVS = (5.0, 45.0, 120.0, 170.0)
TAUS = (0.5, 1.0, 2.0)


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("rough"), rough(129, 3), 33)


@pytest.fixture(scope="module")
def renderer(rough_store):
    s = open_store(rough_store)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    yield r
    r.close()


def views(r: TerrainRenderer, fov: float) -> dict[str, Camera]:
    """An oblique view (as test_gl's), a low view from the ground and one straight down; below
    45 degrees each eye is moved back from its target by ``tan(22.5) / tan(fov / 2)`` (the same
    framing), else a narrow view sees the DEM at full resolution only."""
    x0, ymin, x1, y0 = r.grid.extent
    cx, cy = (x0 + x1) / 2, (ymin + y0) / 2
    zmax = float(np.nanmax(r.store.index.zmax))
    scale = max(1.0, np.tan(np.radians(22.5)) / np.tan(np.radians(fov / 2)))
    kw = {"viewport": SIZE, "near": 5.0, "far": 2e5, "fov_y": fov}
    pairs = {
        "oblique": ((x0 + 600, y0 - 4200, 1600.0), (x0 + 2400, y0 - 2400, 700.0)),
        "ground": ((cx, ymin - 300, zmax + 5), (cx + 200, cy, zmax - 150)),
        "nadir": ((cx + 200, cy - 100, zmax + 900), (cx + 200, cy - 100, zmax - 100)),
    }
    out = {}
    for name, (eye, target) in pairs.items():
        t = np.array(target)
        pos = tuple(t + scale * (np.array(eye) - t))
        out[name] = Camera.look_at(pos, target, up=(0.0, 1.0, 0.0), **kw)
    return out


def errors(r: TerrainRenderer, cam: Camera, tau: float, metric) -> np.ndarray:
    """Measured screen errors (px) of every in-view full-resolution sample."""
    p, _ = r.select(cam, tau, metric)
    return measure.screen_errors(p, r.grid, cam, heights_fn(r.store, p))


@pytest.mark.parametrize("fov", FOVS)
def test_conservative_view_error_is_within_tau(renderer, fov):
    coarser = 0
    for name, cam in views(renderer, fov).items():
        for tau in TAUS:
            p, _ = renderer.select(cam, tau, "conservative-view")
            err = measure.screen_errors(p, renderer.grid, cam, heights_fn(renderer.store, p))
            coarser += int(p.level.min() < renderer.store.k)
            assert err.size > 1000, (name, err.size)
            assert err.max() <= tau, (name, tau, float(err.max()))
    assert coarser > 0  # not only full-resolution selections: the bound is exercised


def quarter(delta, centre_xyz, radius, camera):
    """A quarter of ``conservative-view``: not a bound (the positive control)."""
    return 0.25 * conservative_view(delta, centre_xyz, radius, camera)


def quarter_box(delta, centre_xyz, radius, camera, half_extent):
    """A quarter of ``conservative-view`` on the node's box: not a bound (positive control)."""
    return 0.25 * conservative_view(delta, centre_xyz, radius, camera, half_extent=half_extent)


quarter_box.takes_box = True


def sphere_view(delta, centre_xyz, radius, camera):
    """``conservative-view`` on the old spheres (the block's height range)."""
    return conservative_view(delta, centre_xyz, radius, camera)


@pytest.mark.parametrize("metric", [quarter, quarter_box], ids=["sphere", "box"])
def test_positive_control_a_quarter_of_the_bound_exceeds_tau(renderer, metric):
    worst = max(
        float(errors(renderer, cam, tau, metric).max() / tau)
        for fov in FOVS
        for cam in views(renderer, fov).values()
        for tau in TAUS
    )
    assert worst > 1.0, worst


def test_boxes_draw_fewer_triangles_than_spheres(renderer):
    """Node boxes only tighten: never more triangles than the spheres, fewer in total."""
    box = sph = 0
    for fov in FOVS:
        for cam in views(renderer, fov).values():
            a = patch_counts(renderer.select(cam, 1.0, "conservative-view")[0])
            b = patch_counts(renderer.select(cam, 1.0, sphere_view)[0])
            assert a.triangles <= b.triangles
            box, sph = box + a.triangles, sph + b.triangles
    assert box < sph, (box, sph)
