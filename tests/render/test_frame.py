"""The frame services' public interface, the shared draw with DrawOptions, the one frame step
and the options value of the pipeline (GL)."""

from __future__ import annotations

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

from render.frame import Slot
from render.pipeline import ViewOptions, open_render_session, render_view
from render.renderer import RenderConfig, TerrainRenderer
from render.step import frame_step, stream_step
from render.strategies import get_strategy, strategy_names
from render.strategies.base import DrawOptions
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (96, 72)


@pytest.fixture(scope="module")
def store_path(tmp_path_factory):
    return tile_dem(tmp_path_factory.mktemp("frame"), rough(65, 5), 33)


def _camera() -> Camera:
    return Camera.look_at(
        (500015.0 + 900, 5000000 - 2600, 1400.0), (500015 + 960, 4999040, 800.0),
        viewport=SIZE, near=5.0, far=1e5,
    )  # fmt: skip


def test_slots_levels_and_instances_are_public(store_path, make_renderer):
    r = make_renderer(store_path, size=SIZE, patch_log2=2)
    b = r.store.blocks()[0]
    s = r.slot(b)
    assert isinstance(s, Slot) and s.level == r.store.k == r.gpu_level(b)
    assert r.gpu_level((99, 99)) == -1 and r.height_bytes > 0
    p, _ = r.select(_camera(), 1.0)
    inst = r.instances(p)
    assert sum(len(v) for v in inst.values()) == len(p) and all(
        v.shape[1] == 8 for v in inst.values()
    )
    t = r.patch_table("bound@test", 1)
    assert r.patch_table("bound@test", 1) is t
    r.fill_table(t, [b], "bound")
    assert b in t


@pytest.mark.parametrize("name", strategy_names())
def test_draw_options_equal_keywords(store_path, make_renderer, name):
    r = make_renderer(store_path, size=SIZE, patch_log2=2)
    st = get_strategy(name, r)
    cam = _camera()
    sel, _ = st.select(cam, 1.0)
    a = st.draw(cam, sel, wireframe=True, selection_ms=1.5)
    img_a = r.image()
    b = st.draw(cam, sel, DrawOptions(wireframe=True, selection_ms=1.5))
    assert (a.triangles, a.patches, a.selection_ms) == (b.triangles, b.patches, 1.5)
    np.testing.assert_array_equal(img_a, r.image())
    assert DrawOptions.of(DrawOptions(lod_colour=True), clear=(1, 2, 3)) == DrawOptions(
        lod_colour=True, clear=(1, 2, 3)
    )


def test_frame_step_is_the_manual_sequence(store_path):
    s = open_store(store_path)
    cam = _camera()
    images, stats = [], []
    for use_step in (False, True):
        r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
        st = get_strategy("qiu", r)
        with open_render_session(s, 1.0, "qiu", r.p) as session:
            if use_step:
                step = frame_step(session, st, cam, 1.0)
                res, out = step.resident, step.stats
                assert step.selection_ms == out.selection_ms
            else:
                frame = session.update(cam, wait=True)
                r.sync(frame.blocks, session)
                res = {b: v for b, (v, _) in frame.blocks.items() if v >= 0}
                sel, ms = st.select(cam, 1.0, "qiu", resident=res)
                out = st.draw(cam, sel, selection_ms=ms)
        images.append(r.image())
        stats.append((out.triangles, out.patches, out.max_level, out.min_level, sorted(res)))
        r.close()
    assert stats[0] == stats[1] and stats[0][0] > 0
    np.testing.assert_array_equal(images[0], images[1])


def test_stream_step_without_a_renderer_uploads_nothing(store_path):
    r = TerrainRenderer(open_store(store_path), RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    with open_render_session(r.store, 1.0, "qiu", r.p) as session:
        frame, res = stream_step(session, None, _camera())
        assert res and all(r.gpu_level(b) == -1 for b in res)
        stream_step(session, r, _camera())
        assert all(r.gpu_level(b) == lv for b, lv in res.items())
    r.close()


def test_view_options_equal_keywords(store_path):
    s = open_store(store_path)
    cam = _camera()
    a_img, a = render_view(s, cam, tau=2.0, patch_log2=3, lod="jung-han", wireframe=True)
    o = ViewOptions(lod="jung-han", tau=2.0, patch_log2=3, wireframe=True)
    b_img, b = render_view(s, cam, options=o)
    assert (a.triangles, a.patches) == (b.triangles, b.patches) and a.triangles > 0
    np.testing.assert_array_equal(a_img, b_img)
    with pytest.raises(Exception, match="unknown LOD strategy 'nope'"):
        ViewOptions(lod="nope")


@pytest.mark.parametrize("kind", ["int16", "float32-nodata", "precision"])
def test_block_grid_gathers_the_synced_sessions_levels(tmp_path, kind):
    """A synced session's decoded levels give ``read_block``'s grid (same values and dtype)
    without a store read; a level the session lacks, or no session, is read from the store.
    Control: perturbed session levels change the grid (it is the session's, not a read)."""
    from demtools import write_dem

    from tiler.tile import TileOptions, tile

    data = rough(65, 7)
    kw = {}
    if kind != "int16":
        data = data.astype(np.float32) + np.float32(0.25)
        data[20:40, 10:30] = -9999.0
        kw = {"nodata": -9999.0}
    if kind == "precision":  # quantised: the session decodes from integers again
        src = write_dem(tmp_path / "dem.tif", data * np.float32(1.37), **kw)
        s = tile(src, tmp_path / "q.zarr", TileOptions(block_size=33, precision=0.1, workers=1))
        data = s.read_block((0, 0))
    else:
        s = open_store(tile_dem(tmp_path, data, 33, **kw))
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    reads = []
    read_block = s.read_block
    s.read_block = lambda b, max_level=None, **k: (
        reads.append((b, max_level)) or read_block(b, max_level, **k)
    )
    try:
        assert r.block_grid((0, 0), 2).dtype == data.dtype and len(reads) == 1  # no session
        with open_render_session(s, 1.0, "qiu", r.p) as session:
            frame, res = stream_step(session, r, _camera())
            assert res
            reads.clear()
            for b, lv in res.items():
                for level in range(lv + 1):
                    g = r.block_grid(b, level)
                    want = read_block(b, level)
                    assert g.dtype == want.dtype
                    np.testing.assert_array_equal(g, want)
            assert reads == []  # every grid came from the session
            b, lv = max(res.items(), key=lambda kv: kv[1])
            levels = session.levels(b)
            session.levels = lambda _b: levels[:lv]  # the level evicted meanwhile: read
            np.testing.assert_array_equal(r.block_grid(b, lv), read_block(b, lv))
            assert reads == [(b, lv)]
            session.levels = lambda _b: [v + 1 for v in levels]  # the control
            assert not np.array_equal(r.block_grid(b, lv), read_block(b, lv))
        del session, frame
        reads.clear()
        np.testing.assert_array_equal(r.block_grid(b, lv), read_block(b, lv))
        assert reads == [(b, lv)]  # the closed session holds nothing: read
    finally:
        r.close()


@pytest.fixture(scope="module")
def nodata_path(tmp_path_factory):
    data = rough(65, 5)
    data[10:30, 40:60] = -32768
    return tile_dem(tmp_path_factory.mktemp("frame_nodata"), data, 33, nodata=-32768)


@pytest.mark.parametrize("dem", ["rough", "nodata"])
@pytest.mark.parametrize(
    ("lod", "metric"),
    [
        ("qiu", "qiu"),
        ("jung-han", "qiu"),
        ("geometry-splitting", "qiu"),
        ("seamless-patches", "qiu"),
        ("qiu", "conservative-view"),
    ],
)
def test_streamed_frames_read_nothing_again(store_path, nodata_path, dem, lod, metric):
    """What the strategies build per block from a level's grid, the stored errors or the mask
    (trees, patch tables, node boxes) comes from the streaming session, not from a second
    store read on the render thread. Control: the same selection on a renderer given the
    levels without a session reads them."""
    s = open_store(nodata_path if dem == "nodata" else store_path)
    reads = []
    for name in ("read_block", "read_errors", "read_mask"):
        fn = getattr(s, name)
        setattr(s, name, lambda b, *a, _n=name, _f=fn, **k: reads.append(_n) or _f(b, *a, **k))
    cam = _camera()
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    try:
        with open_render_session(s, 1.0, metric, r.p) as session:
            frame, res = stream_step(session, r, cam)  # (the session reads)
            reads.clear()
            st = get_strategy(lod, r)
            stats = st.draw(cam, st.select(cam, 1.0, metric, resident=res)[0])
            assert stats.triangles > 0 and reads == []
    finally:
        r.close()
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    try:
        reads.clear()
        for b, lv in res.items():
            r.upload(b, s.read_levels(b, lv))  # (a block with nodata: its mask)
        get_strategy(lod, r).select(cam, 1.0, metric, resident=res)
        assert reads  # the control
        if dem == "nodata" and lod != "jung-han":  # (jung-han reads no errors)
            assert {"read_errors", "read_mask"} <= set(reads)
    finally:
        r.close()


def test_masks_leave_with_their_blocks(nodata_path):
    """A block's mask is kept while the block is on the GPU and dropped when it leaves (a long
    flight over a DEM with nodata everywhere does not accumulate every mask it ever saw); a
    block that comes back gets it again and is drawn."""
    s = open_store(nodata_path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2, linger_frames=2), ctx=CTX)
    st = get_strategy("qiu", r)
    cam = _camera()
    try:
        with open_render_session(s, 1.0, "qiu", r.p) as session:
            _, res = stream_step(session, r, cam)
            st.select(cam, 1.0, resident=res)
            masked = {b for b in res if s.index.has_nodata[b]}
            assert masked and r.source.masks_held() == len(res)  # (None: no nodata)
            for _ in range(4):  # nothing in view: every block leaves the GPU
                r.sync({}, session)
            assert not r.pool.slots and r.source.masks_held() == 0
            step = frame_step(session, st, cam, 1.0)
            assert step.stats.triangles > 0 and r.source.masks_held() == len(step.resident)
            assert {b for b in step.resident if r.mask(b) is not None} == masked
    finally:
        r.close()


def test_full_rule_errors_come_derived_from_the_session(nodata_path, monkeypatch):
    """The stored errors with mask boundaries raised (nodata rule "full") are the session
    loaders' (equal to what the renderer derives itself) and the render thread derives no
    mixed nodes for them. Control: without a session it does, and gets the same errors."""
    import streamer.nodata

    true, calls = streamer.nodata.mixed_nodes, []
    monkeypatch.setattr(streamer.nodata, "mixed_nodes", lambda *a: calls.append(1) or true(*a))
    s = open_store(nodata_path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    bare = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    try:
        with open_render_session(s, 1.0, "qiu", r.p) as session:
            _, res = stream_step(session, r, _camera())
            calls.clear()
            got = {b: r.read_errors(b, "full") for b in res}
            assert calls == []
        boundary = [b for b in res if r.mask(b) is not None and not r.mask(b).all()]
        assert boundary  # the scene has mask boundaries
        for b, errors in got.items():
            want = bare.read_errors(b, "full")
            assert errors.keys() == want.keys()
            for name in want:
                for x, y in zip(errors[name], want[name], strict=True):
                    np.testing.assert_array_equal(x, y)
        assert len(calls) == len(boundary)  # the control
    finally:
        r.close()
        bare.close()


def test_geometry_splitting_takes_the_mixed_nodes_from_the_session(nodata_path, monkeypatch):
    """`geometry-splitting`'s trees raise σ at the mask's mixed nodes; with a session those
    come from its loaders (derived once, kept bit-packed) and the render thread derives none:
    the trees equal a bare renderer's. Control: the bare renderer derives them, once per
    block with a mask boundary."""
    import streamer.nodata

    true, calls = streamer.nodata.mixed_nodes, []
    monkeypatch.setattr(streamer.nodata, "mixed_nodes", lambda *a: calls.append(1) or true(*a))
    import render.block_source

    monkeypatch.setattr(render.block_source, "mixed_nodes", streamer.nodata.mixed_nodes)
    s = open_store(nodata_path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    bare = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    try:
        st = get_strategy("geometry-splitting", r)
        st_bare = get_strategy("geometry-splitting", bare)
        with open_render_session(s, 1.0, "qiu", r.p) as session:
            _, res = stream_step(session, r, _camera())
            calls.clear()
            got = {b: st.tree(b, lv) for b, lv in res.items() if lv >= 0}
            assert calls == []
        boundary = [b for b in got if r.mask(b) is not None and not r.mask(b).all()]
        assert boundary  # the scene has mask boundaries
        raised = 0
        for b, tree in got.items():
            want = st_bare.tree(b, res[b])
            for x, y in zip(tree.sigma, want.sigma, strict=True):
                np.testing.assert_array_equal(x, y)
                raised += b in boundary and bool(np.isinf(x).any())
        assert raised >= len(boundary)  # (σ raised where the mask has a boundary)
        assert len(calls) == len(boundary)  # the control
    finally:
        r.close()
        bare.close()


def test_view_options_that_cannot_work_are_refused_naming_them():
    """``ViewOptions(tau=-1, metric="bogus", patch_log2=-3)`` was accepted and failed later,
    in the selection or the shaders; each is refused at once now. The control: numpy
    numbers."""
    import numpy as np
    import pytest

    from render.errors import RenderError
    from render.pipeline import ViewOptions
    from streamer.errors import LodError

    for kw, match in (
        (dict(tau=-1.0), "tau must be a finite"), (dict(tau=float("nan")), "tau must be a finite"),
        (dict(tau="1"), "tau must be a number"), (dict(patch_log2=2.5), "an integer in 1..7"),
        (dict(patch_log2=-3), "in 1..7, got -3"), (dict(patch_log2=0), "cannot be stitched"),
    ):  # fmt: skip
        with pytest.raises(RenderError, match=match):
            ViewOptions(**kw)
    with pytest.raises(LodError, match="unknown metric 'bogus'"):
        ViewOptions(metric="bogus")
    assert ViewOptions(tau=np.float32(2), patch_log2=np.int64(3)).patch_log2 == 3
