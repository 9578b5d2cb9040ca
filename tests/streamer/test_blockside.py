"""The session's side data (streamer.blockside): the error fields and masks its loaders read,
kept under a byte bound for the renderer."""

from __future__ import annotations

import numpy as np
import pytest
from demtools import fractal, write_dem

from streamer.blockside import BlockSide, Side, side_bytes
from streamer.nodata import has_boundary, mixed_nodes, pack_mixed, rule_errors, unpack_mixed
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.errors import LayoutError
from tiler.tile import TileOptions, tile


def _entry(n: int, mask: np.ndarray | None = None) -> Side:
    errors = {"bound": [np.zeros(n, np.uint8)]}
    return Side(errors, mask, errors, None)  # (full shares the arrays: counted once)


def test_least_recently_used_leave_first_and_bytes_stay_bounded():
    side = BlockSide(250)
    side.put((0, 0), _entry(100))
    side.put((0, 1), _entry(100))
    assert side.get((0, 0)) is not None  # now the most recent
    side.put((0, 2), _entry(40, np.ones(20, bool)))  # 260 bytes: the oldest leaves
    assert side.get((0, 1)) is None and side.nbytes == 160
    assert side.get((0, 0)) is not None and side.get((0, 2)).mask.shape == (20,)
    side.put((0, 0), _entry(10))  # replaced: its old bytes released
    assert side.nbytes == 70
    side.put((9, 9), _entry(251))  # larger than the bound: not kept, nothing dropped
    assert side.get((9, 9)) is None and side.nbytes == 70
    assert (side.hits, side.misses) == (3, 2)


def test_kept_arrays_are_read_only():
    side = BlockSide(1 << 20)
    full = {"bound": [np.ones(4, np.float32)]}
    mixed = [np.zeros((1, 1), np.uint8), np.zeros((2, 1), np.uint8)]
    side.put((1, 2), Side({"bound": [np.zeros(4, np.float32)]}, np.ones((3, 3), bool), full, mixed))
    got = side.get((1, 2))
    assert side.nbytes == 16 + 16 + 9 + 3
    for a in (got.errors["bound"][0], got.full["bound"][0], got.mask, got.mixed[1]):
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 0


def test_side_bytes():
    assert side_bytes(0) == 4 << 20
    assert side_bytes(256 << 20) == 32 << 20


@pytest.fixture(scope="module")
def nodata_store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("side")
    data = fractal((257, 321), 5).astype(np.float32)
    data[40:120, 60:200] = np.nan  # nodata across block edges
    src = write_dem(tmp / "d.tif", data, cell=10.0, nodata=float("nan"))
    return tile(src, tmp / "s.zarr", TileOptions(block_size=65, workers=1))


@pytest.mark.parametrize("workers", [0, 2])
def test_a_session_keeps_what_its_loaders_read(nodata_store, workers):
    """Every block whose errors a flight read has the store's stored fields and mask as its side
    data, and the fields under the rule "full" (which differ from the stored ones on this
    store's mask boundaries: the control)."""
    s = nodata_store
    z0, z1 = s.meta.extra["value_range"]
    cams = default_flythrough(s.grid, z0, z1, 40, 30.0, viewport=(320, 240))
    with open_session(s, budget_mb=64, workers=workers) as sess:
        for cam in cams:
            sess.update(cam, wait=True)
        known = sess.loader.errors.known(list(s.blocks()))
        raised = boundaries = 0
        for b in known:
            side = sess.block_side(b)
            stored = s.read_errors(b)
            assert side.errors.keys() == stored.keys() == side.full.keys()
            for name in stored:
                full = rule_errors(s, b, name, "full")[0]
                four = (side.errors[name], side.full[name], stored[name], full)
                for a, f, w, x in zip(*four, strict=True):
                    np.testing.assert_array_equal(a, w)
                    np.testing.assert_array_equal(f, x)
                    raised += not np.array_equal(f, w)
            if s.index.has_nodata[b]:
                np.testing.assert_array_equal(side.mask, s.read_mask(b))
            else:
                assert side.mask is None
            if has_boundary(side.mask):
                mixed = mixed_nodes(side.mask, s.k)[: s.k]
                for a, w in zip(unpack_mixed(side.mixed), mixed, strict=True):
                    np.testing.assert_array_equal(a, w)
                boundaries += 1
            else:
                assert side.mixed is None
        assert len(known) >= 4 and raised >= 1 and boundaries >= 1
        with pytest.raises(LayoutError, match="outside the 4x5-block grid"):
            sess.block_side((99, 99))


def test_mixed_nodes_packed_and_unpacked():
    """A session keeps the mixed nodes bit-packed: the round trip gives them back at every
    depth, widths under a byte included; a packed row is an eighth of its booleans."""
    rng = np.random.default_rng(5)
    for k in (1, 3, 6):
        valid = rng.random(((1 << k) + 1, (1 << k) + 1)) < 0.7
        mixed = mixed_nodes(valid, k)
        packed = pack_mixed(mixed, k)
        n = 1 << (k - 1)  # (rows are packed: a byte at least per row)
        assert len(packed) == k and packed[-1].nbytes == n * max(1, n // 8)
        for a, w in zip(unpack_mixed(packed), mixed[:k], strict=True):
            assert a.dtype == bool
            np.testing.assert_array_equal(a, w)


def test_resident_levels_follow_the_cache_and_what_a_renderer_takes_of_them(nodata_store):
    """`Session.resident_levels()` is the cache's finest level per block after each update and
    its version moves only when it changes; `BlockSource.held_later` gives a block's inputs
    from the session without a store read (the same values as the store's), None for a block
    the session does not hold."""
    from render.block_source import BlockSource
    from tiler.layout import reconstruct

    s = nodata_store
    z0, z1 = s.meta.extra["value_range"]
    cams = default_flythrough(s.grid, z0, z1, 12, 30.0, viewport=(320, 240))
    src = BlockSource(s)
    assert src.held() == {} and src.held_version() is None
    with open_session(s, budget_mb=64, workers=1) as sess:
        src.attach(sess)
        versions = []
        for cam in cams:
            sess.update(cam, wait=True)
            held = sess.resident_levels()
            want = {b: len(sess.levels(b)) - 1 for b in s.blocks() if len(sess.levels(b))}
            assert held == want and src.held() == held
            versions.append(sess.resident_version())
        # the same pose again: the version moves exactly when the levels do (a prefetch read
        # landing between two updates changes them: on a loaded machine it did)
        prev = (sess.resident_version(), sess.resident_levels())
        for _ in range(4):
            sess.update(cams[-1], wait=True)
            now = (sess.resident_version(), sess.resident_levels())
            assert (now[0] == prev[0]) == (now[1] == prev[1]), (prev, now)
            prev = now
        assert versions[0] >= 1 and len(set(versions)) > 1
        b = max(held, key=lambda x: (held[x], x))
        grid_of, errors, mixed_of = src.held_later(b, held[b])
        np.testing.assert_array_equal(grid_of(), reconstruct(s.read_levels(b, held[b]), held[b]))
        for a, w in zip(errors["bound"], s.read_errors(b)["bound"], strict=True):
            np.testing.assert_array_equal(a, w)
        mixed = mixed_of()
        mask = s.read_mask(b)
        if has_boundary(mask):
            for a, w in zip(mixed, mixed_nodes(mask, s.k)[: s.k], strict=True):
                np.testing.assert_array_equal(a, w)
        else:
            assert mixed is None
        assert src.held_later(b, held[b] + 1) is None  # a level it does not hold
        with pytest.raises(LayoutError, match="outside"):
            src.held_later((99, 99), 0)  # a block outside the grid
