"""Direct reads of a remote store's chunks (``tiler.chunkread_remote``) over a loopback HTTP
server: the same values as the local store, one request per level with the shard indexes kept,
a block's levels asked for at once, damage and missing chunks named, a kept index that no longer
matches its shard read again."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

from bench.common import count_requests
from tiler import chunkread, schema
from tiler.chunkread_remote import IndexCache
from tiler.errors import ChunkChecksumError, MissingChunkError
from tiler.store import TerrainStore, open_store
from tiler.tile import TileOptions, tile

K = 6  # blocks of 65²: levels 0..5 sharded, level 6 one chunk per block


def _dem(seed: int) -> np.ndarray:
    dem = fractal((193, 193), seed=seed).astype(np.float32)
    dem[150:175, 20:60] = np.nan  # nodata: mask chunks in the bottom-left blocks
    return dem


@pytest.fixture(scope="module", params=[2, 16], ids=["many-shards", "one-shard"])
def served(request, tmp_path_factory):
    """A 3×3-block store (shards of 2×2 blocks: four shards, or one), its twin tiled from
    other terrain in the same layout, and the folder they are served from."""
    d = tmp_path_factory.mktemp(f"direct{request.param}")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(schema, "SHARD_BLOCKS", request.param)
        for name, seed in (("s", 3), ("other", 4)):
            src = write_dem(d / f"{name}.tif", _dem(seed), nodata=np.nan)
            tile(src, d / f"{name}.zarr", TileOptions(block_size=65))
    return d, request.param


def test_remote_reads_are_direct_and_equal_the_local_store(served):
    d, shard = served
    local = open_store(d / "s.zarr")
    with LoopbackServer(d) as url:
        s = open_store(f"{url}/s.zarr")
        assert s.direct_reads and s.k == K
        assert s._direct["levels/0"].shard == (min(shard, 3), min(shard, 3))
        for b in local.blocks():
            for got, want in zip(s.read_levels_raw(b, K), local.read_levels_raw(b, K), strict=True):
                np.testing.assert_array_equal(got, want)
            for lv in (0, 3, K):
                np.testing.assert_array_equal(s.read_level_raw(b, lv), local.read_level_raw(b, lv))
            np.testing.assert_array_equal(s.read_block(b), local.read_block(b))
            np.testing.assert_array_equal(s.read_block(b, 4), local.read_block(b, 4))
            np.testing.assert_array_equal(s.read_mask(b), local.read_mask(b))
            for name, field in s.read_errors(b).items():
                for got, want in zip(field, local.read_errors(b)[name], strict=True):
                    np.testing.assert_array_equal(got, want)
        assert any(local.index.has_nodata.ravel())  # (masks were read, not only filled)


def test_a_block_is_one_request_per_level_once_its_shard_indexes_are_kept(served):
    """Control: through zarr (``direct_reads=False``) the same reads make two requests per
    sharded level (its shard's index, then the chunk)."""
    d, _ = served
    with LoopbackServer(d) as url:
        s = open_store(f"{url}/s.zarr")
        keys = count_requests(s)
        s.read_levels_raw((0, 0), K)
        assert len(keys) == (K + 1) + 6  # the first block of its shards: their indexes too
        assert s.shard_indexes.fetches == 6
        keys.clear()
        s.read_levels_raw((0, 1), K)  # the same shards (a shard holds 2×2 blocks or more)
        assert len(keys) == K + 1 and s.shard_indexes.fetches == 6
        keys.clear()
        s.read_level_raw((1, 0), 2)
        assert keys == ["levels/2/c/0/0/0"]
        z = TerrainStore(f"{url}/s.zarr", direct_reads=False)
        zkeys = count_requests(z)
        z.read_levels_raw((0, 1), K)
        assert len(zkeys) >= 2 * 6 + 1


@pytest.mark.parametrize(
    ("array", "damage"),
    [("levels/6", "flip"), ("levels/2", "flip"), ("levels/2", "index"), ("mask", "flip")],
)
def test_damage_read_directly_is_named_with_its_block(served, tmp_path, array, damage):
    d, _ = served
    shutil.copytree(d / "s.zarr", tmp_path / "s.zarr")
    b = (2, 0)  # (a block with nodata: it has a mask chunk)
    spec = open_store(tmp_path / "s.zarr")._direct[array]
    path = tmp_path / "s.zarr" / spec.key(b)
    data = bytearray(path.read_bytes())
    if damage == "index":
        at = len(data) - 10  # inside the shard index, before its checksum
    elif spec.shard is None:
        at = len(data) // 2
    else:
        index = bytes(data[-spec.index_nbytes :])
        off, nbytes = chunkread.shard_entry(index, spec, spec.inner(b))
        at = off + nbytes // 2
    data[at] ^= 0x10
    path.write_bytes(bytes(data))
    with LoopbackServer(tmp_path) as url:
        s = open_store(f"{url}/s.zarr")
        read = s.read_mask if array == "mask" else lambda b: s.read_levels_raw(b, K)
        with pytest.raises(ChunkChecksumError, match=rf"block \(2, 0\) \(array '{array}'\)"):
            read(b)
        if array != "mask" and damage == "flip":  # control: the other blocks read
            s.read_levels_raw((0, 0) if spec.shard is None else (0, 2), K)


@pytest.mark.parametrize("array", ["levels/6", "levels/1"])
def test_a_missing_chunk_or_shard_is_named(served, tmp_path, array):
    d, _ = served
    shutil.copytree(d / "s.zarr", tmp_path / "s.zarr")
    spec = open_store(tmp_path / "s.zarr")._direct[array]
    (tmp_path / "s.zarr" / spec.key((1, 1))).unlink()
    with LoopbackServer(tmp_path) as url:
        s = open_store(f"{url}/s.zarr")
        with pytest.raises(MissingChunkError, match=r"level \d of block \(1, 1\)"):
            s.read_levels_raw((1, 1), K)


def test_a_kept_index_that_no_longer_matches_its_shard_is_read_again(served, tmp_path):
    """The shard rewritten under the reader (here: another store's shard in its place): its
    kept index points at the old chunks' places; the read asks for the index again and reads
    the new chunk. Control: read with the kept index, the new shard's bytes fail their
    checksum."""
    d, _ = served
    shutil.copytree(d / "s.zarr", tmp_path / "s.zarr")
    b, level = (1, 1), 4
    with LoopbackServer(tmp_path) as url:
        s = open_store(f"{url}/s.zarr")
        spec = s._direct[f"levels/{level}"]
        s.read_level_raw(b, level)  # its index is kept
        key = spec.key(b)
        kept = s.shard_indexes.get(key)
        shutil.copyfile(d / "other.zarr" / key, tmp_path / "s.zarr" / key)
        new = (tmp_path / "s.zarr" / key).read_bytes()
        old_entry = chunkread.shard_entry(kept, spec, spec.inner(b))
        assert old_entry != chunkread.shard_entry(new[-spec.index_nbytes :], spec, spec.inner(b))
        off, nbytes = old_entry
        with pytest.raises((chunkread.ChecksumMismatch, chunkread.ChunkDecodeError)):
            chunkread.decode_chunk(new[off : off + nbytes], spec)  # the control
        fetches = s.shard_indexes.fetches
        got = s.read_level_raw(b, level)
        np.testing.assert_array_equal(got, open_store(d / "other.zarr").read_level_raw(b, level))
        assert s.shard_indexes.fetches == fetches + 1


def test_the_index_cache_is_bounded():
    c = IndexCache(max_entries=2)
    for i in range(3):
        c.put(f"k{i}", bytes([i]))
    assert len(c) == 2 and c.get("k0") is None and c.get("k2") == b"\x02"
    c.get("k1")  # most recently used: k2 goes first
    c.put("k3", b"\x03")
    assert c.get("k2") is None and c.get("k1") == b"\x01"


def test_ctrl_c_while_a_blocks_levels_are_asked_for_is_raised_and_the_store_reads_on(served):
    """A Ctrl-C while the main thread waits for a block's levels (fetched on zarr's event
    loop, decompressed on the calling thread: nothing writes into its buffers behind it) is
    raised; the next read works."""
    import os
    import signal
    import threading

    d, _ = served
    local = open_store(d / "s.zarr")
    with LoopbackServer(d, latency_s=0.3) as url:
        s = open_store(f"{url}/s.zarr")
        timer = threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT))
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            s.read_block((0, 0))
        timer.join()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        np.testing.assert_array_equal(s.read_block((0, 1)), local.read_block((0, 1)))


def test_reads_of_one_shards_index_under_way_at_once_share_a_request(served):
    """Four blocks of one shard asked for at once with no index kept (a session's loaders
    starting together): one index request. Control: without a cache, one each."""
    from zarr.core.sync import sync

    from tiler.chunkread_remote import fetch_chunks

    d, _ = served  # (shards of 2×2 blocks or more: the four blocks share one)
    local = open_store(d / "s.zarr")
    with LoopbackServer(d) as url:
        for cache in (IndexCache(), None):
            s = open_store(f"{url}/s.zarr")
            keys = count_requests(s)
            spec = s._direct["levels/3"]
            blocks = [(0, 0), (0, 1), (1, 0), (1, 1)]
            got = sync(fetch_chunks(s._remote, [(spec, b) for b in blocks], cache))
            assert len(keys) == len(blocks) + (1 if cache is not None else len(blocks))
            if cache is not None:
                assert cache.fetches == 1 and cache.inflight == {}
            for b, frame in zip(blocks, got, strict=True):
                want = local.read_level_raw(b, 3)
                np.testing.assert_array_equal(chunkread.decompress(frame, spec), want)


def test_an_index_read_across_a_clear_is_not_kept(served):
    """A shard index read while another thread clears the cache (it saw a repair's new
    revision) may predate the rewrite: it was kept after the clear, and later reads of a
    chunk the repair moved took another block's bytes. It is now used for its read and not
    kept, and no read begun after the clear shares it. The control: the same read with no
    clear under way keeps the index."""
    from zarr.abc.store import SuffixByteRequest
    from zarr.core.sync import sync

    from tiler.chunkread_remote import fetch_chunk

    d, _ = served
    local = open_store(d / "s.zarr")
    with LoopbackServer(d) as url:
        s = open_store(f"{url}/s.zarr")
        spec, cache = s._direct["levels/3"], IndexCache()

        class Clearing:  # the store, the cache cleared while an index is on its way
            async def get(self, key, proto, byte_range=None):
                got = await s._remote.get(key, proto, byte_range)
                if isinstance(byte_range, SuffixByteRequest):
                    cache.clear()
                return got

        frame = sync(fetch_chunk(Clearing(), spec, (0, 0), cache))
        want = local.read_level_raw((0, 0), 3)
        np.testing.assert_array_equal(chunkread.decompress(frame, spec), want)
        assert len(cache) == 0 and cache.fetches == 1 and cache.epoch == 1
        assert cache.inflight == {}
        sync(fetch_chunk(s._remote, spec, (0, 0), cache))
        assert len(cache) == 1 and cache.fetches == 2


class _Torn:
    """A remote store whose first ``levels/2`` chunk read (every one, unless ``repaired``)
    answers flipped bytes, as an old index's range over a rewritten shard would; with
    ``repaired`` another thread is made to see a repair (``clear``) just then."""

    def __init__(self, s: TerrainStore, repaired: bool) -> None:
        self.s, self.inner, self.repaired, self.calls = s, s._remote, repaired, 0

    async def get(self, key, proto, byte_range=None):
        got = await self.inner.get(key, proto, byte_range)
        if "levels/2" in key and type(byte_range).__name__ == "RangeByteRequest":
            self.calls += 1
            if self.calls == 1 or not self.repaired:
                raw = bytearray(got.to_bytes())
                raw[len(raw) // 2] ^= 0xFF
                got = proto.buffer.from_bytes(bytes(raw))
                if self.repaired:
                    self.s.shard_indexes.clear()
        return got


@pytest.mark.parametrize("repaired", [True, False])
def test_damage_seen_while_a_repair_is_seen_is_read_again(served, repaired):
    """A read whose chunk range fell across a shard rewritten by a repair (old index, new
    bytes) raised a checksum error and the block was called damaged, though another thread
    saw the repair meanwhile; it is now read again. The control: the same bad bytes with no
    repair seen are damage, named as such."""
    d, _ = served
    local = open_store(d / "s.zarr")
    with LoopbackServer(d) as url:
        s = open_store(f"{url}/s.zarr")
        s._remote = torn = _Torn(s, repaired)
        if repaired:
            got = s.read_level_raw((1, 1), 2)
            np.testing.assert_array_equal(got, local.read_level_raw((1, 1), 2))
            assert torn.calls == 2
        else:
            with pytest.raises(ChunkChecksumError, match=r"\(1, 1\)"):
                s.read_level_raw((1, 1), 2)
