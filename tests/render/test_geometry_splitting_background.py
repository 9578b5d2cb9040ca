"""``geometry-splitting``'s quadtree textures built on a worker thread
(``build_in_background``): what the render thread builds, the interim textures, the final ones
equal to those built at once, errors surfaced, the buffer's growth; on headless EGL."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from gltools import make_context, rough, tile_dem

import render.strategies.geometry_splitting.gl as gs_gl
import render.strategies.geometry_splitting.provision as gs_prov
from render.builds import BuildError
from render.renderer import RenderConfig, TerrainRenderer
from render.strategies import get_strategy
from render.strategies.geometry_splitting import texture_nodes
from streamer.camera import Camera
from tiler.store import open_store

pytestmark = pytest.mark.gl
CTX = make_context()
SIZE = (128, 96)
X0, Y0 = 500015.0, 5000000.0 - 15
CAM = Camera.look_at(
    (X0 + 600, Y0 - 4200, 1600.0), (X0 + 2400, 4997600, 700.0), viewport=SIZE, near=5.0
)


@pytest.fixture(scope="module")
def store_k7(tmp_path_factory):
    """257² rough terrain in four 129² blocks (k = 7: above the provisional level 6)."""
    return tile_dem(tmp_path_factory.mktemp("k7"), rough(257, 5), 129)


@pytest.fixture
def threads_of_builds(monkeypatch):
    """The names of the threads ``build_tree`` and ``packed_tree`` ran on, with the level of
    their grid."""
    seen: list[tuple[str, int]] = []
    real = gs_prov.build_tree

    def spy(grid_of, *args):
        grid = grid_of()
        seen.append((threading.current_thread().name, (grid.shape[0] - 1).bit_length() - 1))
        return real(lambda: grid, *args)

    def spy_packed(bound, grid, mixed, depth=None):
        seen.append((threading.current_thread().name, (grid.shape[0] - 1).bit_length() - 1))
        return real_packed(bound, grid, mixed, depth=depth)

    real_packed = gs_prov.packed_tree
    monkeypatch.setattr(gs_prov, "build_tree", spy)
    monkeypatch.setattr(gs_prov, "packed_tree", spy_packed)  # (textures below full resolution)
    return seen


def _renderer(path, level: int) -> TerrainRenderer:
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    for b in s.blocks():
        r.upload(b, s.read_levels(b, level))
    return r


def _raise(r: TerrainRenderer, level: int) -> None:
    for b in r.store.blocks():
        r.upload(b, r.store.read_levels(b, level))


def _texture(st, b) -> bytes:
    """The texture the GPU holds for ``b`` (as deep as it is stored node by node)."""
    return st._tex.read(b)


def _want(path, b, level: int) -> bytes:
    """The texture a strategy that builds at once uploads for ``b`` at ``level``."""
    r = _renderer(path, level)
    try:
        st = get_strategy("geometry-splitting", r)
        return st.tree(b, level).packed(st._depth(b, level)).tobytes()
    finally:
        r.close()


def test_a_level_change_is_built_off_the_render_thread(store_k7, threads_of_builds):
    r = _renderer(store_k7, 3)
    st = get_strategy("geometry-splitting", r)
    try:
        assert st.build_in_background()
        st.select(CAM, 1.0)  # new blocks at level 3 (<= 6): built at once, here
        assert {lv for _, lv in threads_of_builds} == {3}
        assert {name for name, _ in threads_of_builds} == {threading.current_thread().name}
        threads_of_builds.clear()
        _raise(r, 7)
        sel, _ = st.select(CAM, 1.0)
        blocks = list(r.store.blocks())
        assert sorted(st.interim_blocks()) == sorted(blocks)  # drawn with level 3's meanwhile
        assert st.leaf_nodes(sel)[:, 1].max() > 3  # (the heights' level is the cap)
        here = [lv for name, lv in threads_of_builds if name == threading.current_thread().name]
        assert here == []  # nothing built in the frame
        # level 3's textures are compact (depths past 3 one entry per depth-3 node: the store's
        # error cap is 3); read past it, they give what the CPU twin gets from their trees
        assert {st._tex.depth[b] for b in r.store.blocks()} == {3}
        counts, leaves, _ = st.expand_reference(CAM, 1.0)
        got = st.leaf_nodes(sel)
        assert sel.pass_counts == counts
        np.testing.assert_array_equal(got[np.lexsort(got.T[::-1])], leaves)
        me = threading.current_thread().name  # (the twin's level-3 trees, built here)
        threads_of_builds[:] = [x for x in threads_of_builds if x != (me, 3)]
        st.settle()
        st.select(CAM, 1.0)  # uploads what the worker built
        assert st.interim_blocks() == []
        assert all(name.startswith("terrastream-block-build") for name, _ in threads_of_builds)
        assert sorted(lv for _, lv in threads_of_builds) == [7] * len(blocks)
        for b in blocks:  # the same texture as one built in the frame
            assert _texture(st, b) == _want(store_k7, b, 7)
    finally:
        st.close()
        r.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("terrastream-block-build")]


def test_control_without_background_builds_the_frame_builds_them(store_k7, threads_of_builds):
    r = _renderer(store_k7, 3)
    st = get_strategy("geometry-splitting", r)
    try:
        st.select(CAM, 1.0)
        threads_of_builds.clear()
        _raise(r, 7)
        st.select(CAM, 1.0)
        assert st.interim_blocks() == []
        me = threading.current_thread().name
        assert threads_of_builds == [(me, 7)] * len(list(r.store.blocks()))
        assert st.build_ms > 0.0
    finally:
        r.close()


def test_a_new_fine_block_is_drawn_with_a_provisional_texture(store_k7, threads_of_builds):
    r = _renderer(store_k7, 7)
    st = get_strategy("geometry-splitting", r)
    try:
        st.build_in_background()
        sel, _ = st.select(CAM, 1.0)
        me = threading.current_thread().name
        assert {lv for name, lv in threads_of_builds if name == me} == {gs_gl.PROVISIONAL_LEVEL}
        assert sel.triangles > 0  # drawn in its first frame
        b = (0, 0)
        assert _texture(st, b) == _want(store_k7, b, gs_gl.PROVISIONAL_LEVEL)
        st.settle()
        st.select(CAM, 1.0)
        assert st.interim_blocks() == []
        assert _texture(st, b) == _want(store_k7, b, 7)
        # the selection is then the one built at once gives
        ref = get_strategy("geometry-splitting", r)
        want, _ = ref.select(CAM, 1.0)
        got, _ = st.select(CAM, 1.0)
        np.testing.assert_array_equal(st.leaf_nodes(got), ref.leaf_nodes(want))
    finally:
        st.close()
        r.close()


def test_a_failed_background_build_is_raised_on_the_render_thread(store_k7, monkeypatch):
    r = _renderer(store_k7, 3)
    st = get_strategy("geometry-splitting", r)
    try:
        st.build_in_background()
        st.select(CAM, 1.0)

        def broken(*_a):
            raise MemoryError("no room for the tree")

        monkeypatch.setattr(gs_prov, "build_tree", broken)
        _raise(r, 7)
        st.select(CAM, 1.0)
        st.settle()  # (waits: a failed build is done too)
        with pytest.raises(BuildError, match="geometry-splitting quadtree texture"):
            st.select(CAM, 1.0)
    finally:
        st.close()
        r.close()


def test_growing_the_buffer_keeps_every_texture(tmp_path, monkeypatch):
    monkeypatch.setattr(gs_gl, "TEXTURE_MIN_BYTES", 0)  # (else room for the 64 blocks at once)
    path = tile_dem(tmp_path, rough(257, 9), 33)  # 64 blocks of 33²
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    try:
        st = get_strategy("geometry-splitting", r)
        blocks = list(s.blocks())
        first, rest = blocks[:3], blocks[3:]
        for b in first:
            r.upload(b, s.read_levels(b, 3))
        st.select(CAM, 1.0)
        size0 = st._tex.nbytes
        for b in rest:
            r.upload(b, s.read_levels(b, 5))
        st.select(CAM, 1.0)
        assert st._tex.nbytes > size0  # (grown: the first blocks' textures copied)
        for b in blocks:
            lv = 3 if b in first else 5
            assert _texture(st, b) == st.tree(b, lv).packed(st._depth(b, lv)).tobytes()
    finally:
        r.close()


def _churn(path, steps: int) -> list[int]:
    """Four blocks on the GPU at a time, the window sliding one block a frame (as along a
    flight); the texture buffer's bytes after each frame, every drawn texture checked."""
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    sizes = []
    try:
        st = get_strategy("geometry-splitting", r)
        blocks = list(s.blocks())
        for i in range(steps):
            window = blocks[i : i + 4]
            for b in list(r.pool.slots):
                if b not in window:
                    r.pool.release(b)
            for b in window:
                if r.gpu_level(b) < 0:
                    r.upload(b, s.read_levels(b, 3 + i % 3))
            st.select(CAM, 1.0)
            sizes.append(st.own_gpu_bytes())
            for b in window:  # a reused slot holds its new block's texture, the others theirs
                lv = r.gpu_level(b)
                assert _texture(st, b) == st.tree(b, lv).packed(st._depth(b, lv)).tobytes()
        return sizes
    finally:
        r.close()


@pytest.mark.parametrize("cache_textures", [0, 6])
def test_released_blocks_free_their_texture_slots(tmp_path, monkeypatch, cache_textures):
    path = tile_dem(tmp_path, rough(257, 9), 33)  # 64 blocks of 33², k = 5
    per_bytes = texture_nodes(5, 4) * 8  # the largest texture (levels 3-5: depth 3 or 4)
    monkeypatch.setattr(gs_gl, "TEXTURE_CACHE_BYTES", cache_textures * per_bytes)
    monkeypatch.setattr(gs_gl, "TEXTURE_MIN_BYTES", 0)  # (else the whole store's 64 blocks)
    sizes = _churn(path, 40)
    # twice the live blocks' largest textures, or the cache of departed blocks', all along
    assert max(sizes) <= max(2 * 4, cache_textures) * per_bytes
    assert sizes[-1] == max(sizes)


def test_control_without_releases_the_buffer_grows_with_the_blocks_seen(tmp_path, monkeypatch):
    from render.strategies.geometry_splitting.slots import SlotTable

    monkeypatch.setattr(SlotTable, "release_all_but", lambda self, live: [])
    path = tile_dem(tmp_path, rough(257, 9), 33)
    monkeypatch.setattr(gs_gl, "TEXTURE_CACHE_BYTES", 0)
    monkeypatch.setattr(gs_gl, "TEXTURE_MIN_BYTES", 0)
    assert max(_churn(path, 40)) >= 40 * texture_nodes(5, 3) * 8  # (the smallest texture)


def _leave_and_return(path, monkeypatch) -> list[int]:
    """Blocks 0-3 drawn, block 0 dropped while 4 arrives, then 0 back (4 dropped); how many
    textures the render thread built in each of the three frames (each texture checked)."""
    s = open_store(path)
    r = TerrainRenderer(s, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    built: list[list[int]] = []
    real = gs_gl.GeometrySplitting._texture

    def spy(self, b, lv):
        built[-1].append(b)
        return real(self, b, lv)

    monkeypatch.setattr(gs_gl.GeometrySplitting, "_texture", spy)
    try:
        st = get_strategy("geometry-splitting", r)
        blocks = list(s.blocks())
        for i, (gone, come) in enumerate([((), blocks[:4]), (blocks[:1], blocks[4:5]),
                                          (blocks[4:5], blocks[:1])]):  # fmt: skip
            built.append([])
            for b in gone:
                r.pool.release(b)
            for b in come:
                r.upload(b, s.read_levels(b, 4))
            st.select(CAM, 1.0)
            for b in r.pool.slots:
                assert _texture(st, b) == st.tree(b, 4).packed(st._depth(b, 4)).tobytes(), (i, b)
        return [len(x) for x in built]
    finally:
        r.close()


def test_a_block_back_before_its_slot_is_taken_keeps_its_texture(tmp_path, monkeypatch):
    path = tile_dem(tmp_path, rough(257, 9), 33)
    assert _leave_and_return(path, monkeypatch) == [4, 1, 0]


def test_control_without_revival_the_returning_block_is_rebuilt(tmp_path, monkeypatch):
    from render.strategies.geometry_splitting.textures import TextureStore

    monkeypatch.setattr(TextureStore, "revive", lambda self, b: False)
    path = tile_dem(tmp_path, rough(257, 9), 33)
    assert _leave_and_return(path, monkeypatch) == [4, 1, 1]


@pytest.fixture(scope="module")
def store_k7_nodata(tmp_path_factory):
    """``store_k7``'s terrain with a nodata hole across all four blocks' meeting corner."""
    dem = rough(257, 5).astype(np.float32)
    dem[100:160, 90:170] = np.nan
    return tile_dem(tmp_path_factory.mktemp("k7nd"), dem, 129)


@pytest.mark.parametrize("bits", [True, False])
def test_an_interim_texture_of_a_block_with_nodata_reads_its_mixed_nodes(
    store_k7_nodata, monkeypatch, bits
):
    """A block with nodata drawn finer than its (compact) texture reads σ = ∞ at its mixed
    nodes past the texture's depth from the bitmask: the selection is the CPU twin's (from the
    texture's tree, σ = ∞ per mixed node). At τ = 64 only those nodes split past depth 3.
    Control: the bitmask flag left out of the block table, the selection is not the twin's."""
    if not bits:
        monkeypatch.setattr(gs_gl.TextureStore, "bits", lambda self, b: False)
    r = _renderer(store_k7_nodata, 3)
    st = get_strategy("geometry-splitting", r)
    try:
        st.build_in_background()
        st.select(CAM, 64.0)  # level 3 textures: compact (cap 3), a bitmask where nodata
        assert all(st._tex.depth[b] == 3 for b in r.store.blocks())
        assert any(len(st._tex.read(b)) > texture_nodes(7, 3) * 8 for b in r.store.blocks())
        _raise(r, 7)
        sel, _ = st.select(CAM, 64.0)  # drawn at 7 with level 3's textures meanwhile
        assert sorted(st.interim_blocks()) == sorted(r.store.blocks())
        counts, leaves, _ = st.expand_reference(CAM, 64.0)
        got = st.leaf_nodes(sel)
        assert leaves[:, 1].max() > 3  # mixed nodes split past the textures' depth
        same = sel.pass_counts == counts and np.array_equal(got[np.lexsort(got.T[::-1])], leaves)
        assert same is bits
    finally:
        st.close()
        r.close()


@pytest.mark.parametrize("min_bytes", [16 << 20, 0])
def test_a_store_that_fits_the_first_buffer_never_moves_a_texture(
    store_k7_nodata, monkeypatch, min_bytes
):
    """Four 129² blocks' full textures fit the 16 MiB first buffer: every slot is a full
    texture's, so compact textures growing to full ones at a level change move nothing (the
    buffer is never replaced). Control: with no first-buffer minimum the slots are the
    textures' sizes and the change reallocates."""
    monkeypatch.setattr(gs_gl, "TEXTURE_MIN_BYTES", min_bytes)
    r = _renderer(store_k7_nodata, 3)
    st = get_strategy("geometry-splitting", r)
    try:
        st.select(CAM, 1.0)  # compact level-3 textures
        buf = st._tex.buf
        _raise(r, 7)
        st.select(CAM, 1.0)  # full ones (no background: built in the frame)
        for b in r.store.blocks():
            assert st._tex.read(b) == st.tree(b, 7).packed(st._depth(b, 7)).tobytes()
        assert (st._tex.buf is buf) is (min_bytes > 0)
    finally:
        r.close()


def _ahead_run(path, threads_of_builds, per_frame: int, lower: int = 0):
    """A session holding every block in view; the strategy draws one of them for a few
    frames (the worker idle otherwise), then all (the others ``lower`` levels below their
    first texture's level, as if the session had changed their level after it was built):
    the strategy, renderer, levels, first block, the render thread's level builds in that
    last frame and that frame's selection."""
    from render.step import resident_levels
    from streamer.session import open_session

    store = open_store(path)
    r = TerrainRenderer(store, RenderConfig(size=SIZE, patch_log2=2), ctx=CTX)
    st = get_strategy("geometry-splitting", r)
    st.build_in_background()
    st.ahead.per_frame = per_frame
    with open_session(store, budget_mb=64, workers=1, tau=1.0, culling="hull") as s:
        frame = s.update(CAM, wait=True)
        r.sync(frame.blocks, s)
        res = resident_levels(frame)
        first = min(res)
        assert len(res) >= 3 and s.resident_levels() == res
        for _ in range(6):  # one block drawn; the others are the session's, not drawn
            st.select(CAM, 1.0, resident={first: res[first]})
            st.settle()
        mark = len(threads_of_builds)
        if lower:
            cap = gs_prov.PROVISIONAL_LEVEL
            res = {b: lv if b == first else min(lv, cap) - lower for b, lv in res.items()}
            assert min(res.values()) >= 0
        sel, _ = st.select(CAM, 1.0, resident=res)
        me = threading.current_thread().name
        built_here = [lv for name, lv in threads_of_builds[mark:] if name == me]
        return st, r, res, first, built_here, sel


@pytest.mark.parametrize("name", ["store_k7", "store_k7_nodata"])
def test_first_textures_are_built_ahead_for_the_sessions_blocks(
    request, name, threads_of_builds, monkeypatch
):
    if name == "store_k7_nodata":  # first textures at level 4: compact (the cap is 3), so a
        monkeypatch.setattr(gs_prov, "PROVISIONAL_LEVEL", 4)  # block with nodata adds its bitmask
    st, r, res, first, built_here, sel = _ahead_run(
        request.getfixturevalue(name), threads_of_builds, 2
    )
    try:
        others = [b for b in res if b != first]
        assert built_here == []  # no texture built on the render thread for the new blocks
        assert st.ahead.hits == len(others) and st.ahead.ready == {}
        for b in others:  # the same bytes the render thread would have built
            lv = min(res[b], gs_prov.PROVISIONAL_LEVEL)
            assert st._tex.level[b] == lv
            assert _texture(st, b) == st._texture(b, lv)[0]
        # with nodata, textures carrying the bitmask of their mixed nodes (the session's)
        assert any(st._tex.bits(b) for b in others) is (name == "store_k7_nodata")
    finally:
        st.close()
        r.close()


def test_control_without_builds_ahead_the_render_thread_builds_them(store_k7, threads_of_builds):
    st, r, res, first, built_here, sel = _ahead_run(store_k7, threads_of_builds, 0)
    try:
        assert len(built_here) == len(res) - 1 and st.ahead.hits == 0
    finally:
        st.close()
        r.close()


def test_a_first_texture_built_for_another_level_is_drawn_until_the_blocks_own_is_built(
    store_k7, threads_of_builds
):
    """The session changed a held block's level after its first texture was built ahead: the
    block is drawn with that texture (an interim one, as after a level change on the GPU) and
    its own is built on the level worker, not on the render thread."""
    st, r, res, first, built_here, sel = _ahead_run(store_k7, threads_of_builds, 2, lower=1)
    try:
        others = [b for b in res if b != first]
        assert built_here == []  # nothing built on the render thread
        # (the one miss: the block drawn from the first frame, before anything was held)
        assert (st.ahead.hits, st.ahead.misses, st.ahead.interims) == (0, 1, len(others))
        built = {b: res[b] + 1 for b in others}  # (the level the session held them at)
        for b in others:  # drawn meanwhile with the texture built ahead
            assert st._tex.level[b] == built[b]
            assert _texture(st, b) == st._texture(b, built[b])[0]
        assert sorted(st.interim_blocks(res)) == sorted(others)
        # drawn deeper than its level (texture 6, heights 5): what the CPU twin gets from the
        # texture's tree
        counts, leaves, _ = st.expand_reference(CAM, 1.0, res)
        got = st.leaf_nodes(sel)
        assert sel.pass_counts == counts
        np.testing.assert_array_equal(got[np.lexsort(got.T[::-1])], leaves)
        mark = len(threads_of_builds)
        st.settle()
        st.select(CAM, 1.0, resident=res)  # uploads the worker's builds
        assert st.interim_blocks(res) == []
        me = threading.current_thread().name
        assert [lv for name, lv in threads_of_builds[mark:] if name == me] == []
        worker = sorted(lv for name, lv in threads_of_builds if name == "terrastream-block-build_0")
        assert all(worker.count(res[b]) >= 1 for b in others)  # (built there)
        for b in others:  # the texture the render thread would have built for the level
            assert st._tex.level[b] == res[b]
            assert _texture(st, b) == st._texture(b, res[b])[0]
    finally:
        st.close()
        r.close()


def test_control_a_first_texture_of_another_level_refused_is_built_on_the_render_thread(
    store_k7, threads_of_builds, monkeypatch
):
    """Control: taking only a texture built for the level drawn (the code before interims),
    the render thread builds the first textures of those blocks itself."""
    real = gs_prov.AheadTextures.take

    def same_level_only(self, b, level):
        got = real(self, b, level)
        return got if got is None or got[0] == level else None

    monkeypatch.setattr(gs_prov.AheadTextures, "take", same_level_only)
    st, r, res, first, built_here, sel = _ahead_run(store_k7, threads_of_builds, 2, lower=1)
    try:
        others = [b for b in res if b != first]
        assert sorted(built_here) == sorted(res[b] for b in others)
        assert st.interim_blocks(res) == []
    finally:
        st.close()
        r.close()
