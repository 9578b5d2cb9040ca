"""The store layout built in memory and written at once, or created concurrently, equals the one
created array by array through the store."""

from __future__ import annotations

import contextlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zarr
from demtools import fractal

from tiler import encoding, schema
from tiler.content import CONTENT_KEY
from tiler.info import store_info
from tiler.store import open_store
from tiler.tile import TileOptions, tile


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def diff_stores(a: Path, b: Path) -> list[str]:
    """Files (metadata and chunks) that differ between two layouts, byte for byte."""
    fa, fb = _files(a), _files(b)
    return sorted(k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k))


@pytest.fixture
def meta(dem_factory, tmp_path):
    """A real store's metadata (3 x 3 blocks of 17², 5 levels, padding)."""
    tile(dem_factory(fractal((40, 40), 1)), tmp_path / "s.zarr", TileOptions(block_size=17))
    return open_store(tmp_path / "s.zarr").meta


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("method", ["memory", "concurrent"])
@pytest.mark.parametrize("compact", [False, True])
def test_layout_methods_are_byte_identical(meta, tmp_path, version, method, compact):
    m = replace(meta, format_version=version)
    with schema.compact_metadata() if compact else contextlib.nullcontext():
        for name, how in (("seq", "sequential"), (method, method)):
            group = zarr.open_group(tmp_path / name, mode="w")
            schema.create_layout(group, m, 3, method=how)
    assert diff_stores(tmp_path / "seq", tmp_path / method) == []
    arrays = {p for p, _ in schema.layout_specs(m, 3)}
    content = {"index/content"} if m.extra.get(CONTENT_KEY) else set()  # (tiler.content)
    assert arrays == set(schema.array_names(m.k)) | content  # every array of the format, once
    assert (tmp_path / method / "order_index" / "c" / "0" / "0").is_file()  # the tables' data
    assert not list((tmp_path / method).rglob("*.partial"))


def test_memory_layout_into_a_zarr_store_object(meta):
    """A store that is not a local directory (here zarr's MemoryStore) gets the same keys and
    bytes, written in one gather."""
    from zarr.storage import MemoryStore

    stores = {how: MemoryStore() for how in ("sequential", "memory")}
    for how, st in stores.items():
        schema.create_layout(zarr.open_group(st, mode="w"), meta, 3, method=how)
    a, b = (dict(st._store_dict) for st in stores.values())
    assert a.keys() == b.keys() and len(a) > 20
    assert all(a[k].to_bytes() == b[k].to_bytes() for k in a)


def test_layout_comparison_sees_a_difference(meta, tmp_path):
    """Positive control: another compression level changes the compared metadata files."""
    schema.create_layout(zarr.open_group(tmp_path / "a", mode="w"), meta, 3, method="sequential")
    schema.create_layout(zarr.open_group(tmp_path / "b", mode="w"), meta, 4)
    diff = diff_stores(tmp_path / "a", tmp_path / "b")
    assert "levels/0/zarr.json" in diff and "errors/zarr.json" in diff
    assert "order_index/zarr.json" not in diff  # the tables keep their own level


@pytest.mark.parametrize("method", schema.LAYOUT_METHODS)
def test_layout_refuses_an_existing_array(meta, tmp_path, method):
    g = zarr.open_group(tmp_path / "x", mode="w")
    schema.create_layout(g, meta, 3)
    before = _files(tmp_path / "x")
    with pytest.raises(Exception, match="levels|exists|already"):
        schema.create_layout(g, meta, 3, method=method)
    if method == "memory":  # refused before anything was written
        assert _files(tmp_path / "x") == before


def test_memory_layout_refuses_an_existing_array_in_a_store_object(meta):
    from zarr.storage import MemoryStore

    g = zarr.open_group(MemoryStore(), mode="w")
    schema.create_layout(g, meta, 3)
    with pytest.raises(zarr.errors.ContainsArrayError, match="levels/0"):
        schema.create_layout(g, meta, 3)


def test_layout_method_is_checked(meta, tmp_path):
    with pytest.raises(ValueError, match="method='fast'"):
        schema.create_layout(zarr.open_group(tmp_path / "y", mode="w"), meta, 3, method="fast")


def _blosc(group: zarr.Group, name: str) -> dict:
    """The blosc configuration of array ``name`` (inside the shard for sharded levels)."""
    codecs = group[name].metadata.to_dict()["codecs"]
    if codecs[0]["name"] == "sharding_indexed":
        codecs = codecs[0]["configuration"]["codecs"]
    return next(c["configuration"] for c in codecs if c["name"] == "blosc")


@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_level_shuffle_follows_the_encoding(dem_factory, tmp_path, dtype):
    """An integer store bit shuffles its two finest levels and byte shuffles the rest (sharded
    and not); a float store byte shuffles all; ``meta.compressor`` names the bit-shuffled
    levels; the errors stay byte shuffled; lossless."""
    data = fractal((300, 300), 1, dtype)
    tile(dem_factory(data), tmp_path / "s.zarr", TileOptions(block_size=65))
    store = open_store(tmp_path / "s.zarr")
    group = zarr.open_group(tmp_path / "s.zarr", mode="r")
    k = store.meta.k
    want = [k - 1, k] if dtype == "int16" else []
    assert store.meta.compressor["bitshuffle_levels"] == want
    for i in range(store.meta.levels):
        shuffle = "bitshuffle" if i in want else "shuffle"
        assert _blosc(group, f"levels/{i}")["shuffle"] == shuffle
        assert schema.level_bits(store.meta.compressor, i) == (i in want)
    assert _blosc(group, "errors")["shuffle"] == "shuffle"
    text = store_info(str(tmp_path / "s.zarr"))["compressor"]
    assert ("bit shuffled" in text) == bool(want) and (f"levels {k - 1}, {k}" in text) == bool(want)
    assert ("byte shuffled in blocks at most 50% terrain where at most 5% larger" in text) == bool(
        want
    )
    assert np.array_equal(store.read_block((1, 2)), data[64:129, 128:193])
    assert np.array_equal(store.read_block((1, 2), k - 2), data[64:129:4, 128:193:4])


def test_bitshuffle_levels_at_small_k():
    """The two finest levels, never a negative one."""
    assert schema.bitshuffle_levels("int-residual", 10) == [9, 10]
    assert schema.bitshuffle_levels("int-residual", 0) == [0]
    assert schema.bitshuffle_levels("float-xor", 10) == []


def test_an_older_store_keeps_byte_shuffle(meta):
    """A store whose metadata names no bit-shuffled levels (written before the choice) is
    described by its byte-shuffled layout (the metadata, not the encoding, decides)."""
    old = replace(meta, compressor={"name": schema.COMPRESSOR_NAME, "level": 3})
    specs = dict(schema.layout_specs(old, 3))
    shuffles = {specs[f"levels/{i}"]["compressors"][0].shuffle.value for i in range(meta.levels)}
    assert shuffles == {"shuffle"}
    new = dict(schema.layout_specs(meta, 3))
    assert new[f"levels/{meta.k}"]["compressors"][0].shuffle.value == "bitshuffle"
    assert new["levels/0"]["compressors"][0].shuffle.value == "shuffle"


@pytest.mark.parametrize("seed", [1, 3])
def test_bit_shuffle_is_smaller_on_the_finest_integer_levels(seed):
    """The measurement behind the choice, level by level as the store compresses them (each
    level its own chunk): bit shuffle beats byte shuffle on each level a store bit shuffles,
    and all levels concatenated into one buffer (not what a store does) would say the
    opposite."""
    from numcodecs import Blosc

    def size(raw: np.ndarray, sh: int) -> int:
        return len(Blosc("zstd", 3, sh, blocksize=schema.LEVEL_BLOCKSIZE).encode(raw))

    levels = encoding.encode_levels(fractal((257, 257), seed), 8)
    for i in schema.bitshuffle_levels("int-residual", 8):
        assert size(levels[i], Blosc.BITSHUFFLE) < size(levels[i], Blosc.SHUFFLE)
    joined = np.concatenate(levels)
    assert size(joined, Blosc.BITSHUFFLE) > size(joined, Blosc.SHUFFLE)


@pytest.mark.parametrize("k", [2, 4, 8, 9, 10, 11, 12])
def test_table_blocks_are_whole_powers_of_two(k):
    """Bit shuffle needs whole blocks: the tables' block is a power of two <= their bytes."""
    from tiler.layout import order_index

    n = order_index(k).nbytes
    b = schema.table_blocksize(n)
    cap = min(n, schema.TABLE_MAX_BLOCK)
    assert b & (b - 1) == 0 and b <= cap and 2 * b > cap


def test_table_blocksize_shrinks_the_order_table():
    """k = 8's order table in one block that is not a multiple of 8 values compresses far
    worse (the failure ``table_blocksize`` avoids) than in the chosen block."""
    from numcodecs import Blosc

    from tiler.layout import order_index

    t = np.ascontiguousarray(order_index(8))
    chosen = Blosc("zstd", 5, Blosc.BITSHUFFLE, blocksize=schema.table_blocksize(t.nbytes))
    whole = Blosc("zstd", 5, Blosc.BITSHUFFLE, blocksize=t.nbytes)
    assert len(chosen.encode(t)) * 4 < len(whole.encode(t))


def test_store_metadata_is_written_compact(dem_factory, tmp_path):
    """Every zarr.json of a tiled store is one line (no indentation); zarr's own default for
    other groups in the process is left as it was (positive control: that one is indented)."""
    tile(dem_factory(fractal((40, 40), 1)), tmp_path / "s.zarr", TileOptions(block_size=17))
    files = list((tmp_path / "s.zarr").rglob("zarr.json"))
    assert len(files) >= 19  # root, 3 groups, 5 levels, errors, mask, 7 index, 2 tables
    assert all(b"\n" not in p.read_bytes().strip() for p in files)
    zarr.open_group(tmp_path / "other.zarr", mode="w", attributes={"a": 1})
    assert b"\n" in (tmp_path / "other.zarr" / "zarr.json").read_bytes().strip()
    assert open_store(tmp_path / "s.zarr").meta.complete


def test_memory_layout_refuses_a_read_only_store(meta, tmp_path):
    zarr.open_group(tmp_path / "r", mode="w")
    g = zarr.open_group(zarr.storage.LocalStore(tmp_path / "r", read_only=True), mode="r")
    with pytest.raises(ValueError, match="read-only"):
        schema.create_layout(g, meta, 3)
    assert not (tmp_path / "r" / "levels").exists()


def test_a_failed_layout_write_leaves_no_partial_file(meta, tmp_path, monkeypatch):
    """A write that fails (disk full) removes its temporary file and raises."""
    import os

    real = os.replace
    calls = []

    def failing(src, dst):
        calls.append(dst)
        if len(calls) == 5:
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(OSError, match="No space"):
        schema.create_layout(zarr.open_group(tmp_path / "f", mode="w"), meta, 3)
    monkeypatch.undo()
    assert len(calls) == 5 and not list((tmp_path / "f").rglob("*.partial"))
