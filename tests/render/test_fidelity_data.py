"""Fidelity at the extremes (issue 12), the data side: heights far from zero without jitter
(heights relative to the store's reference height, subtracted in float64 before float32)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from demtools import fractal
from gltools import make_context, tile_dem

from render import measure
from render.gpu import MASKED_BELOW
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy, strategy_names
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
NAMES = strategy_names()
OPTIONS = {
    "chunk-tessellation": {"chunk_log2": 3},
    "chunk-tessellation-gpu": {"chunk_log2": 3},
    "seamless-patches": {"res_log2": 3},
}
EVEREST = 8848.0
#: pixel budgets: share of pixels whose largest channel differs by more than 2 levels
PLATEAU_BUDGET, MOVE_BUDGET = 0.01, 0.01


def _relief() -> np.ndarray:
    """5 cm of relief on a 65² float64 DEM (1 m cells)."""
    d = fractal((65, 65), seed=4).astype(np.float64)
    return 0.05 * (d - d.min()) / np.ptp(d)


@pytest.fixture(scope="module")
def plateaus(tmp_path_factory):
    rel = _relief()
    return {
        z0: tile_dem(tmp_path_factory.mktemp(f"p{int(z0)}"), rel + z0, 65, cell=1.0)
        for z0 in (0.0, EVEREST)
    }


def _image(path, name, z0, dx=0.0):
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy(name, r, **OPTIONS.get(name, {}))
    g = r.grid
    cam = Camera.look_at(
        (g.x0 + 32 + dx, g.y0 - 75.0, z0 + 12.0), (g.x0 + 32 + dx, g.y0 - 32, z0), viewport=SIZE,
        near=0.05, far=1e4,
    )  # fmt: skip
    sel, _ = st.select(cam, 0.0)
    st.draw(cam, sel)
    img = r.image().astype(int)
    r.close()
    return img


def _changed(a, b) -> float:
    return float((np.abs(a - b).max(-1) > 2).mean())


@pytest.mark.parametrize("name", NAMES)
def test_a_plateau_at_8848_m_renders_like_the_same_relief_at_0_m(plateaus, name):
    low = _image(plateaus[0.0], name, 0.0)
    high = _image(plateaus[EVEREST], name, EVEREST)
    diff = _changed(low, high)
    assert diff <= PLATEAU_BUDGET, f"{diff:.1%} of the pixels differ"


@pytest.mark.parametrize("name", NAMES)
def test_a_millimetre_camera_move_at_8848_m_changes_few_pixels(plateaus, name):
    a = _image(plateaus[EVEREST], name, EVEREST)
    b = _image(plateaus[EVEREST], name, EVEREST, dx=0.001)
    diff = _changed(a, b)
    assert diff <= MOVE_BUDGET, f"{diff:.1%} of the pixels changed"


# -- nodata at every τ -------------------------------------------------------------------------

NODATA = -9999
SQUARE = 64


def _checkerboard(n: int = 257) -> tuple[np.ndarray, np.ndarray]:
    """A rough DEM whose 64-sample squares (offset by 32, so they straddle blocks) alternate
    between terrain and nodata; the DEM and its validity mask."""
    r, c = np.mgrid[0:n, 0:n]
    dem = 800 + 40 * np.sin(c / 9.0) * np.cos(r / 7.0) + 0.2 * ((r * 7 + c * 13) % 17)
    valid = ((r + 32) // SQUARE + (c + 32) // SQUARE) % 2 == 1
    return np.where(valid, np.rint(dem), NODATA).astype(np.int16), valid


@pytest.fixture(scope="module")
def checkerboard(tmp_path_factory):
    dem, valid = _checkerboard()
    return tile_dem(tmp_path_factory.mktemp("cb"), dem, 65, nodata=NODATA), valid


def coverage(st, camera: Camera, sel, valid: np.ndarray) -> tuple[float, float]:
    """Shares of the in-view terrain samples and of the in-view nodata samples that the drawn
    surface covers (the strategy's CPU twin of what it drew, on the sample lattice)."""
    if hasattr(st, "triangles"):  # what the GPU drew (qiu's CPU twin is half-open at edges)
        tri, th = st.triangles(camera, sel)
        ok = (th > MASKED_BELOW).all(axis=1)
        rows, cols, h = measure.rasterise(tri[ok], th[ok])
    else:
        rows, cols, h = st.surface(camera, sel)
    covered = np.zeros(valid.shape, bool)
    inside = (rows >= 0) & (rows < valid.shape[0]) & (cols >= 0) & (cols < valid.shape[1])
    inside &= np.isfinite(h) & (h > MASKED_BELOW)  # a triangle touching nodata is not drawn
    covered[rows[inside], cols[inside]] = True
    g = st.r.grid
    rr, cc = np.mgrid[0 : valid.shape[0], 0 : valid.shape[1]]
    x, y = g.sample_xy(rr.ravel(), cc.ravel())
    seen = camera.in_view(np.c_[x, y, np.full(x.size, 800.0)]).reshape(valid.shape)
    terrain, holes = valid & seen, ~valid & seen
    assert terrain.sum() > 1000 and holes.sum() > 1000
    return covered[terrain].mean(), covered[holes].mean()


#: (strategy, options): every strategy with its default nodata rule, and qiu's "gap" rule
NODATA_CASES = [(n, OPTIONS.get(n, {})) for n in NAMES] + [("qiu", {"nodata": "gap"})]


@pytest.mark.parametrize(("name", "opts"), NODATA_CASES, ids=[f"{n}-{o}" for n, o in NODATA_CASES])
def test_checkerboard_nodata_at_tau_4_draws_the_terrain_and_not_the_holes(checkerboard, name, opts):
    path, valid = checkerboard
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=(256, 256), patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy(name, r, **opts)
    g = r.grid
    x0, y0, x1, y1 = g.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + 9500.0), pitch=-90.0, viewport=(256, 256),
                 near=1.0, far=1e5)  # fmt: skip
    sel, _ = st.select(cam, 4.0)
    st.draw(cam, sel)
    drawn, bridged = coverage(st, cam, sel, valid)
    r.close()
    assert drawn >= 0.99, f"{drawn:.1%} of the terrain samples drawn"
    assert bridged <= 0.01, f"{bridged:.1%} of the nodata samples covered"


@pytest.mark.parametrize("tau", [1.0, 4.0])
def test_seamless_paper_rho_keeps_the_nodata_rule(checkerboard, tau):
    """Livny et al.'s ρ reads nothing from the data, but a node mixing terrain and nodata
    still gets ρ = ∞ (full resolution at mask boundaries). Positive control: the same patches
    at their coarsest tiles drop terrain samples."""
    path, valid = checkerboard
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=(256, 256), patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy("seamless-patches", r, res_log2=3, rho="paper")
    g = r.grid
    x0, y0, x1, y1 = g.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + 9500.0), pitch=-90.0, viewport=(256, 256),
                 near=1.0, far=1e5)  # fmt: skip
    sel, _ = st.select(cam, tau)
    drawn, bridged = coverage(st, cam, sel, valid)
    coarse = dataclasses.replace(sel, edge_level=sel.edge_level * 0 + sel.depth[:, None] + 1)
    drawn_coarse, _ = coverage(st, cam, coarse, valid)
    r.close()
    assert drawn >= 0.99 and bridged <= 0.01, (drawn, bridged)
    assert drawn_coarse < 0.95, drawn_coarse


def test_the_session_streams_what_the_nodata_boundaries_need(checkerboard):
    """Through the frame step the session loads full resolution at the mask boundaries (the
    loader raises the same errors), so nothing is drawn coarser than wanted."""
    from render.pipeline import render_view

    path, valid = checkerboard
    s = open_store(path)
    x0, y0, x1, y1 = s.grid.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + 9500.0), pitch=-90.0, viewport=(256, 256),
                 near=1.0, far=1e5)  # fmt: skip
    full, _ = render_view(s, cam, tau=0.0, patch_log2=2)
    img, stats = render_view(s, cam, tau=4.0, patch_log2=2)
    clear = np.array(RenderConfig().clear)
    share = (~(img == clear).all(-1)).mean() / (~(full == clear).all(-1)).mean()
    assert stats.clamped == 0 and share >= 0.99, (stats.clamped, share)


def _streamed(path, rule: str, tau: float, altitude: float) -> tuple[int, int, int]:
    """qiu with the nodata ``rule`` through the frame step over the checkerboard, straight
    down from ``altitude``: the session's loaded bytes, triangles drawn and nodes clamped."""
    from render.pipeline import open_render_session
    from render.step import frame_step

    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=(256, 256), patch_log2=2), ctx=CTX)
    st = get_strategy("qiu", r, nodata=rule)
    x0, y0, x1, y1 = s.grid.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + altitude), pitch=-90.0,
                 viewport=(256, 256), near=1.0, far=1e6)  # fmt: skip
    with open_render_session(s, tau, "qiu", r.p, nodata=rule) as session:
        step = frame_step(session, st, cam, tau, "qiu")
        loaded = session.summary()["loaded_bytes"]
    r.close()
    return loaded, step.stats.triangles, step.stats.clamped


@pytest.mark.parametrize(("tau", "altitude"), [(1.0, 20000.0), (1.0, 40000.0), (4.0, 40000.0)])
def test_the_session_streams_what_the_gap_rule_draws(checkerboard, tau, altitude, monkeypatch):
    """With the nodata rule "gap" the session plans with the gap widths too: it loads fewer
    bytes than under "full" and the renderer, drawing with "gap", is never clamped (every level
    it draws is resident). Positive control: a session planned with the stored errors alone
    (the gap widths dropped) leaves nodes clamped."""
    import streamer.loader

    path, _ = checkerboard
    full = _streamed(path, "full", tau, altitude)
    gap = _streamed(path, "gap", tau, altitude)
    assert full[2] == 0 and gap[2] == 0, (full, gap)
    assert gap[0] < full[0] and gap[1] < full[1], (full, gap)
    true = streamer.loader.rule_errors_of
    monkeypatch.setattr(
        streamer.loader, "rule_errors_of", lambda *a: (true(*a)[0], None)
    )  # the stored errors alone
    assert _streamed(path, "gap", tau, altitude)[2] > 0


@pytest.mark.parametrize("tau", [0.0, 4.0])
def test_qius_cpu_twin_is_what_the_gpu_drew(checkerboard, tau):
    """The crack and coverage figures use qiu's CPU twin of its mesh (``triangles``); it must be
    the mesh the GPU drew (``gpu_triangles``, read back): same triangles, same heights."""
    path, _ = checkerboard
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=(256, 256), patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy("qiu", r)
    x0, y0, x1, y1 = r.grid.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + 9500.0), pitch=-90.0, viewport=(256, 256),
                 near=1.0, far=1e5)  # fmt: skip
    sel, _ = st.select(cam, tau)
    cpu_tri, cpu_h = st.triangles(cam, sel)
    gpu_tri, gpu_h = st.gpu_triangles(cam, sel)
    r.close()

    def drawn(tri, h):  # drawn triangles as a sorted set of (corners, heights) rows
        ok = np.isfinite(h).all(axis=1) & (h > MASKED_BELOW).all(axis=1)
        u, v = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        area = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
        ok &= area != 0  # snapped-away triangles are degenerate in both
        rows = np.concatenate([tri[ok].reshape(-1, 6), np.round(h[ok], 3)], axis=1)
        return rows[np.lexsort(rows.T[::-1])]

    a, b = drawn(cpu_tri, cpu_h), drawn(gpu_tri, gpu_h)
    assert len(a) > 0 and a.shape == b.shape
    np.testing.assert_array_equal(a, b)


def _gap_view(path, rule: str, tau: float):
    """qiu on the checkerboard from 40 km straight down (about 6 samples a pixel): triangles
    and the pipeline's coverage figures (:func:`render.coverage.coverage`)."""
    from render import coverage as cov

    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=(256, 256), patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, s.k))
    st = get_strategy("qiu", r, nodata=rule)
    x0, y0, x1, y1 = r.grid.extent
    cam = Camera(((x0 + x1) / 2, (y0 + y1) / 2, 800 + 40000.0), pitch=-90.0, viewport=(256, 256),
                 near=1.0, far=1e6)  # fmt: skip
    sel, _ = st.select(cam, tau)
    tri, th = st.triangles(cam, sel)
    ref, _ = st.select_full(cam)
    c = cov.coverage(r.grid, cam, ref, measure.heights_fn(s, ref), tri, th)
    r.close()
    return len(tri), c


@pytest.mark.parametrize("tau", [0.5, 4.0])
def test_gap_rule_leaves_only_sub_pixel_gaps(checkerboard, tau, monkeypatch):
    """The nodata rule "gap" draws mixed cells coarser where they are small on screen: fewer
    triangles than "full", the dropped terrain reported (coverage < 1) and every undrawn
    terrain sample within min(τ, 1) px of drawn terrain, no hole drawn over. Positive control:
    cell widths understated 8× leave undrawn samples more than a pixel away."""
    from render.frame import FrameServices

    path, _ = checkerboard
    n_full, full = _gap_view(path, "full", tau)
    n_gap, gap = _gap_view(path, "gap", tau)
    assert full.terrain_covered == 1.0 and full.uncovered_px == 0.0
    assert n_gap < n_full / 3 and gap.nodata_covered == 0.0
    assert 0.85 < gap.terrain_covered < 1.0, gap
    assert 0.0 < gap.uncovered_px <= min(tau, 1.0), gap
    true = FrameServices.gap_field
    monkeypatch.setattr(FrameServices, "gap_field", lambda self, b: [w / 8 for w in true(self, b)])
    _, broken = _gap_view(path, "gap", tau)
    assert broken.uncovered_px > 1.0, broken
