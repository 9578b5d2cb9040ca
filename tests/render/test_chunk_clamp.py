"""A one-shot view (``render``, ``tradeoff``) of ``chunk-tessellation`` draws its chunks at
their own level: its session plans levels with the chunks' size (``2**c`` cells), not the
renderer's smaller patches (which loaded levels coarser than the chunks, drawn with
``clamped 0``); a chunk still drawn below its own level counts as clamped and re-streams the
view. And ``tradeoff``'s reference is full resolution even where every stored error is 0."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, tile_dem

import render.pipeline as pipeline
from render.pipeline import ViewOptions, render_view, tradeoff
from render.select import coarse_leaves, uncounted_clamps
from render.strategies import get_strategy
from render.strategies.qiu import patch_counts
from render.views import make_camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
make_context()
VIEW = (256, 192)
CHUNKS = ["chunk-tessellation", "chunk-tessellation-gpu"]


@pytest.fixture(scope="module")
def rough_store(tmp_path_factory):
    """257² of noisy hills (30 m cells) in 2 x 2 blocks of 129² (k = 7: chunks of 32 cells at
    c = 5) whose 16-cell patches meet τ = 4 from the overview where 32-cell chunks do not."""
    y, x = np.mgrid[0:257, 0:257]
    noise = np.random.default_rng(0).normal(0.0, 5.0, (257, 257))
    data = (200.0 + 150.0 * np.sin(x / 20.0) * np.cos(y / 25.0) + noise).astype(np.float32)
    return open_store(tile_dem(tmp_path_factory.mktemp("chunk_clamp"), data, 129, cell=30.0))


@pytest.fixture(scope="module")
def flat_store(tmp_path_factory):
    """257² of one height: every stored error is 0."""
    data = np.full((257, 257), 800, dtype=np.int16)
    return open_store(tile_dem(tmp_path_factory.mktemp("chunk_flat"), data, 129))


def _with_all_data(store, cam, lod, tau):
    """The strategy's own selection with every block in view at full resolution (compare's
    session): its row."""
    return tradeoff(store, cam, [tau], repeats=1, stream_tau=0.0, options=ViewOptions(lod))[0]


@pytest.mark.parametrize("lod", CHUNKS)
def test_render_and_tradeoff_draw_the_chunks_the_full_data_gives(rough_store, lod):
    cam = make_camera(rough_store, VIEW)
    tau = 4.0
    full = _with_all_data(rough_store, cam, lod, tau)
    _, st = render_view(rough_store, cam, options=ViewOptions(lod, tau))
    row = tradeoff(rough_store, cam, [tau], repeats=1, options=ViewOptions(lod))[0]
    assert st.clamped == 0 and row.clamped == 0 and full.clamped == 0
    assert st.triangles == row.triangles == full.triangles > 0
    assert row.stream_tau == tau  # the session at tau already held the chunks' levels
    assert row.max_screen_error_px == full.max_screen_error_px


@pytest.mark.parametrize("lod", CHUNKS)
def test_chunks_drawn_below_their_level_count_as_clamped_and_restream(
    rough_store, lod, monkeypatch
):
    cam = make_camera(rough_store, VIEW)
    tau = 4.0
    full = _with_all_data(rough_store, cam, lod, tau)
    # the old plan (the renderer's 16-cell patches) loads levels below the 32-cell chunks
    monkeypatch.setattr(pipeline, "session_patch_log2", lambda strat, r: r.p)
    _, st = render_view(rough_store, cam, options=ViewOptions(lod, tau))
    row = tradeoff(rough_store, cam, [tau], repeats=1, options=ViewOptions(lod))[0]
    assert st.clamped == 0 and row.clamped == 0
    assert st.triangles == row.triangles == full.triangles
    assert row.stream_tau < tau  # re-streamed: the first session's chunks were too coarse
    monkeypatch.setattr(pipeline, "RESTREAM", ())  # the control: one session at tau
    _, once = render_view(rough_store, cam, options=ViewOptions(lod, tau))
    assert once.clamped > 0 and once.triangles < full.triangles


def test_uncounted_clamps_are_the_leaves_capped_below_their_own_level(make_renderer, rough_store):
    r = make_renderer(rough_store, size=VIEW, patch_log2=4)
    strat = get_strategy("chunk-tessellation", r)
    cam = make_camera(rough_store, VIEW)
    k, c, tau = r.k, strat.c, 1e6  # nothing wants to split: every chunk stops at depth 0
    sel, _ = strat.select(cam, tau, resident={b: k for b in rough_store.blocks()})
    assert uncounted_clamps(sel, k, c, tau) == 0 and not coarse_leaves(sel, k, c).any()
    capped, _ = strat.select(cam, tau, resident={b: c - 1 for b in rough_store.blocks()})
    coarse = coarse_leaves(capped, k, c)
    assert coarse.any() and capped.clamped == 0  # the walk's own count misses them
    assert uncounted_clamps(capped, k, c, tau) == int(coarse.sum())
    assert uncounted_clamps(capped, k, c, tau, min_depth=capped.depth.max() + 1) == 0


def test_tradeoff_reference_is_full_resolution_where_errors_are_0(flat_store, make_renderer):
    cam = make_camera(flat_store, VIEW)
    r = make_renderer(flat_store, size=VIEW, patch_log2=4)  # every block uploaded at level k
    full, _ = r.select(cam, 0.0, "qiu", full=True)
    want = patch_counts(full).triangles
    assert full.clamped == 0 and (full.level == r.k).all()
    row = tradeoff(flat_store, cam, [0.01], repeats=1)[0]
    assert row.reference_triangles == want
    assert row.triangles < want  # errors 0: the selection itself stays coarse
