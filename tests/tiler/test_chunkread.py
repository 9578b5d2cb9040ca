"""Direct level reads (tiler.chunkread): same values and the same integrity errors as zarr's."""

from __future__ import annotations

import json
import shutil

import google_crc32c
import numpy as np
import pytest
import zarr
from demtools import fractal
from storetools import flip_bit

from tiler import chunkread, encoding
from tiler.errors import ChunkChecksumError, MissingChunkError, StoreChangedError
from tiler.layout import level_end
from tiler.store import TerrainStore, open_store
from tiler.tile import TileOptions, tile

SHARDED, PLAIN = 3, 6  # with block_size 65 (k = 6): levels 0..5 sharded, level 6 not


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """3x3-block stores (k = 6), tiled once: int16 with nodata, float32, uint8."""
    d = tmp_path_factory.mktemp("chunkread")
    from demtools import write_dem

    ints = fractal((150, 150), 31)
    ints[10:20, 100:130] = -9999
    write_dem(d / "i.tif", ints, nodata=-9999)
    write_dem(d / "f.tif", fractal((150, 150), 32, "float32"))
    write_dem(d / "u.tif", fractal((150, 150), 36, "uint8"))
    for name in ("i", "f", "u"):
        tile(d / f"{name}.tif", d / f"{name}.zarr", TileOptions(block_size=65))
    return d


def _copy(stores, tmp_path, name="i"):
    shutil.copytree(stores / f"{name}.zarr", tmp_path / "s.zarr")
    return tmp_path / "s.zarr"


@pytest.mark.parametrize("name", ["i", "f", "u"])
def test_direct_reads_equal_zarr_reads(stores, name):
    direct = open_store(stores / f"{name}.zarr")
    via_zarr = TerrainStore(stores / f"{name}.zarr", direct_reads=False)
    assert direct.direct_reads and not via_zarr.direct_reads
    for b in direct.grid.blocks():
        for level in range(direct.k + 1):
            got, ref = direct.read_level_raw(b, level), via_zarr.read_level_raw(b, level)
            assert got.dtype == ref.dtype and np.array_equal(got, ref), (b, level)
            np.testing.assert_array_equal(
                direct.read_block(b, level), via_zarr.read_block(b, level)
            )
        for g, r in zip(direct.read_levels(b, 4), via_zarr.read_levels(b, 4), strict=True):
            np.testing.assert_array_equal(g, r)


def test_read_block_results_do_not_share_the_scratch_buffer(stores):
    s = open_store(stores / "i.zarr")
    a = s.read_block((0, 0))
    keep = a.copy()
    b = s.read_block((2, 2))
    assert not np.array_equal(a, b)  # the two blocks differ...
    np.testing.assert_array_equal(a, keep)  # ...and the second read left the first alone
    raws = s.read_levels_raw((1, 1), s.k)
    assert encoding.joined(raws, s.k).base is raws[0].base  # one sequence, no copy
    n = level_end(s.k) + 1  # read_block's per-thread buffer: its views join without a copy too
    scratch = s._scratch(n)
    joined = encoding.joined(s._levels_raw((1, 1), s.k, scratch), s.k)
    assert joined.base is scratch.base and np.array_equal(joined, np.concatenate(raws))


def test_joined_is_a_view_only_for_consecutive_views():
    seq = np.arange(25, dtype=np.uint16)
    parts = [seq[0:4], seq[4:9], seq[9:25]]
    view = encoding.joined(parts, 2)
    assert view.base is seq and np.array_equal(view, seq)
    shuffled = [seq[0:4], seq[4:9], seq[9:25].copy()]  # positive control: not one array
    assert encoding.joined(shuffled, 2).base is not seq
    assert np.array_equal(encoding.joined(shuffled, 2), seq)
    gap = [seq[0:4], seq[5:10]]  # right sizes, wrong place
    assert np.array_equal(encoding.joined(gap, 1), np.r_[seq[0:4], seq[5:10]])


@pytest.mark.parametrize("level", [PLAIN, SHARDED])
def test_bit_flip_in_a_chunk_raises_a_checksum_error_on_both_paths(stores, tmp_path, level):
    root = _copy(stores, tmp_path)
    spec = open_store(root)._direct[f"levels/{level}"]
    path = root / spec.key((1, 2))
    data = bytearray(path.read_bytes())
    if spec.shard is None:
        flip_bit(path, np.random.default_rng(level))
    else:  # inside block (1, 2)'s inner chunk, not the shard index
        off, nbytes = _entries(data, spec)[spec.inner((1, 2))]
        data[off + nbytes // 2] ^= 0x10
        path.write_bytes(bytes(data))
    for s in (open_store(root), TerrainStore(root, direct_reads=False)):
        with pytest.raises(ChunkChecksumError, match=rf"level {level} of block \(1, 2\)") as ei:
            s.read_block((1, 2))
        assert ei.value.level == level and ei.value.array == f"levels/{level}"
    open_store(root).read_block((0, 0))  # the others still read


def test_damaged_shard_index_is_a_checksum_error(stores, tmp_path):
    root = _copy(stores, tmp_path)
    shard = root / "levels" / str(SHARDED) / "c" / "0" / "0" / "0"
    data = bytearray(shard.read_bytes())
    data[-7] ^= 1  # inside the index (its last entry)
    shard.write_bytes(bytes(data))
    with pytest.raises(ChunkChecksumError, match="shard index"):
        open_store(root).read_block((1, 1))


def test_missing_chunk_and_missing_shard_entry_raise(stores, tmp_path):
    root = _copy(stores, tmp_path)
    (root / "levels" / str(PLAIN) / "c" / "2" / "1" / "0").unlink()
    s = open_store(root)
    with pytest.raises(MissingChunkError, match=rf"level {PLAIN} of block \(2, 1\)"):
        s.read_block((2, 1))
    # an inner chunk the shard index marks absent (index rewritten with a valid checksum)
    spec = s._direct[f"levels/{SHARDED}"]
    path = root / spec.key((0, 1))
    data = bytearray(path.read_bytes())
    body = np.frombuffer(bytes(data[-spec.index_nbytes : -4]), dtype="<u8").reshape(-1, 2).copy()
    body[spec.inner((0, 1))] = chunkread.EMPTY
    index = body.tobytes()
    data[-spec.index_nbytes :] = index + google_crc32c.value(index).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    for reader in (open_store(root), TerrainStore(root, direct_reads=False)):
        with pytest.raises(MissingChunkError, match=rf"level {SHARDED} of block \(0, 1\)"):
            reader.read_level_raw((0, 1), SHARDED)
    open_store(root).read_level_raw((0, 0), SHARDED)  # its neighbours in the shard still read


def test_truncated_chunk_is_an_error(stores, tmp_path):
    root = _copy(stores, tmp_path)
    path = root / "levels" / str(PLAIN) / "c" / "0" / "0" / "0"
    path.write_bytes(path.read_bytes()[:-9])
    with pytest.raises(ChunkChecksumError, match=rf"level {PLAIN} of block \(0, 0\)"):
        open_store(root).read_block((0, 0))


def test_store_changed_check_fires_on_direct_reads(dem_factory, tmp_path):
    tile(
        dem_factory(fractal((150, 150), 33), "a.tif"),
        tmp_path / "s.zarr",
        TileOptions(block_size=65),
    )
    reader = open_store(tmp_path / "s.zarr")
    assert reader.direct_reads
    reader.read_block((0, 0))
    b = dem_factory(fractal((150, 150), 34), "b.tif")
    tile(b, tmp_path / "s.zarr", TileOptions(block_size=65, overwrite=True))
    for read in (lambda: reader.read_block((0, 0)), lambda: reader.read_level_raw((0, 0), 2)):
        with pytest.raises(StoreChangedError, match="replaced or rewritten"):
            read()


def test_other_codec_chains_are_left_to_zarr(stores):
    meta = zarr.open_array(stores / "i.zarr", path=f"levels/{PLAIN}", mode="r").metadata.to_dict()
    assert chunkread.level_spec("levels/6", meta) is not None
    for change in (
        lambda m: m["codecs"].pop(),  # no crc32c (format 1)
        lambda m: m["codecs"].insert(1, {"name": "gzip", "configuration": {"level": 1}}),
        lambda m: m["codecs"].__setitem__(0, {"name": "bytes", "configuration": {"endian": "big"}}),
        lambda m: m.__setitem__("data_type", "int16"),
    ):
        m = json.loads(json.dumps(meta))
        change(m)
        assert chunkread.level_spec("levels/6", m) is None
    shard = zarr.open_array(stores / "i.zarr", path="levels/2", mode="r").metadata.to_dict()
    m = json.loads(json.dumps(shard))
    assert chunkread.level_spec("levels/2", m).shard == (3, 3)
    m["codecs"][0]["configuration"]["index_location"] = "start"
    assert chunkread.level_spec("levels/2", m) is None
    m = json.loads(json.dumps(meta))  # bytes without an endianness: only for one-byte types
    m["codecs"][0] = {"name": "bytes"}
    assert chunkread.level_spec("levels/6", m) is None
    m["data_type"] = "uint8"
    assert chunkread.level_spec("levels/6", m) is not None


def _entries(data: bytearray, spec: chunkread.LevelSpec) -> np.ndarray:
    return np.frombuffer(bytes(data[-spec.index_nbytes : -4]), dtype="<u8").reshape(-1, 2)


@pytest.mark.parametrize("name", ["i", "f", "u"])
def test_errors_and_mask_read_directly_equal_zarr_reads(stores, name):
    direct = open_store(stores / f"{name}.zarr")
    via_zarr = TerrainStore(stores / f"{name}.zarr", direct_reads=False)
    assert {"errors", "mask"} <= direct._direct.keys() and not via_zarr._direct
    nodata = 0
    for b in direct.grid.blocks():
        e_d, e_z = direct.read_errors(b), via_zarr.read_errors(b)
        assert e_d.keys() == e_z.keys()
        for f in e_d:
            for a, z in zip(e_d[f], e_z[f], strict=True):
                assert a.dtype == z.dtype and np.array_equal(a, z, equal_nan=True)
        m_d, m_z = direct.read_mask(b), via_zarr.read_mask(b)
        assert m_d.dtype == m_z.dtype == bool and np.array_equal(m_d, m_z)
        nodata += int(direct.index.has_nodata[b])
    assert name != "i" or nodata  # the int store has nodata blocks: their masks were read


def test_errors_and_mask_damage_is_caught_on_the_direct_path(stores, tmp_path):
    root = _copy(stores, tmp_path)
    s = open_store(root)
    holes = [b for b in s.grid.blocks() if s.index.has_nodata[b]]
    plain = [b for b in s.grid.blocks() if not s.index.has_nodata[b]]
    assert holes and plain
    errors = root / s._direct["errors"].key((1, 1))
    flip_bit(errors, np.random.default_rng(9))
    with pytest.raises(ChunkChecksumError, match=r"errors of block \(1, 1\)"):
        open_store(root).read_errors((1, 1))
    (root / s._direct["errors"].key((0, 0))).unlink()
    with pytest.raises(MissingChunkError, match=r"errors of block \(0, 0\)"):
        open_store(root).read_errors((0, 0))
    mask = root / s._direct["mask"].key(holes[0])
    assert mask.exists() and not (root / s._direct["mask"].key(plain[0])).exists()
    assert open_store(root).read_mask(plain[0]).all()  # no chunk written: zarr's fill
    mask.unlink()
    for reader in (open_store(root), TerrainStore(root, direct_reads=False)):
        with pytest.raises(MissingChunkError, match="mask of block"):
            reader.read_mask(holes[0])


def test_errors_and_mask_of_other_chains_are_left_to_zarr(stores):
    for name in ("errors", "mask"):
        meta = zarr.open_array(stores / "i.zarr", path=name, mode="r").metadata.to_dict()
        spec = chunkread.block_spec(name, meta)
        assert spec is not None and spec.shape == tuple(meta["shape"][2:])
        m = json.loads(json.dumps(meta))
        m["codecs"].pop()  # no crc32c
        assert chunkread.block_spec(name, m) is None
        m = json.loads(json.dumps(meta))
        m["chunk_grid"]["configuration"]["chunk_shape"] = [1, 1, 1, meta["shape"][3]]
        assert chunkread.block_spec(name, m) is None
