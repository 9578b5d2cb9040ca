"""Direct chunk writes (tiler.chunkwrite) write zarr's bytes, atomically, and only where zarr's
chain is what they encode."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import zarr
from demtools import fractal

from tiler import chunkwrite
from tiler import run as run_mod
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


def _chunks(root: Path) -> dict[str, bytes]:
    """Every chunk file of the arrays block workers write (levels, errors, mask)."""
    out = {}
    for top in ("levels", "errors", "mask"):
        for p in (root / top).rglob("*"):
            if p.is_file() and p.name != "zarr.json":
                out[str(p.relative_to(root))] = p.read_bytes()
    return out


def _tile_both(monkeypatch, src: Path, tmp_path: Path, **kw) -> tuple[Path, Path, int]:
    """The same job tiled with direct writes and through zarr; the direct chunk writes made
    (none in the zarr run: the switch is honoured)."""
    calls = []

    def counting(real):
        def f(*a, **k):
            calls.append(a[1].name)
            return real(*a, **k)

        return f

    for name in ("write_local", "write_local_bytes"):  # the latter: sparse blocks' chosen frames
        monkeypatch.setattr(chunkwrite, name, counting(getattr(chunkwrite, name)))
    direct, ref = tmp_path / "direct.zarr", tmp_path / "zarr.zarr"
    tile(src, direct, TileOptions(**kw))
    n_direct = len(calls)
    monkeypatch.setenv(run_mod.DIRECT_WRITES_ENV, "0")
    tile(src, ref, TileOptions(**kw))
    assert len(calls) == n_direct
    return direct, ref, n_direct


@pytest.mark.parametrize(
    ("dtype", "holes"), [("int16", False), ("int16", True), ("float32", True), ("uint8", False)]
)
def test_direct_writes_are_zarrs_bytes(monkeypatch, dem_factory, tmp_path, dtype, holes):
    """Every level, error and mask chunk is byte-identical to zarr's write of it (bit- and
    byte-shuffled levels, a bool mask), and the direct path really wrote them."""
    data = fractal((300, 280), 2, dtype)
    nodata = None
    if holes:
        nodata = -9999 if dtype != "uint8" else 0
        data[100:140, 20:170] = nodata
    src = dem_factory(data, nodata=nodata)
    direct, ref, n = _tile_both(monkeypatch, src, tmp_path, block_size=129, workers=1)
    a, b = _chunks(direct), _chunks(ref)
    assert a.keys() == b.keys() and len(a) > 20
    assert [k for k in a if a[k] != b[k]] == []
    meta = open_store(direct).meta
    assert meta.k == 7  # levels 6 and 7 are written per block (0-5 are sharded)
    per_block = meta.k + 1 - run_mod.small_levels(meta.k) + 1  # levels written per block + errors
    assert n >= meta.grid.shape[0] * meta.grid.shape[1] * per_block
    assert verify_store(direct).ok
    assert np.array_equal(open_store(direct).read_block((1, 2)), open_store(ref).read_block((1, 2)))


def test_a_wrong_encoder_is_caught(monkeypatch, dem_factory, tmp_path):
    """Positive control: a writer whose blosc differs from zarr's (byte instead of bit shuffle
    on the finest levels) makes chunks that the comparison above tells apart."""
    real = chunkwrite.chunk_spec

    def wrong(name, metadata):
        spec = real(name, metadata)
        if spec is not None and spec.codec.shuffle == 2:
            spec.codec.shuffle = 1
        return spec

    monkeypatch.setattr(chunkwrite, "chunk_spec", wrong)
    direct, ref, _ = _tile_both(
        monkeypatch, dem_factory(fractal((300, 280), 2)), tmp_path, block_size=129, workers=1
    )
    a, b = _chunks(direct), _chunks(ref)
    assert [k for k in a if a[k] != b[k]]


def _spec_of(path: Path, name: str) -> chunkwrite.ChunkSpec | None:
    return chunkwrite.chunk_spec(name, zarr.open_array(path, path=name).metadata.to_dict())


def test_only_the_chain_it_encodes(dem_factory, tmp_path):
    """Sharded small levels and other chains are left to zarr; the written arrays qualify."""
    tile(dem_factory(fractal((300, 280), 2)), tmp_path / "s.zarr", TileOptions(block_size=129))
    s = tmp_path / "s.zarr"
    k = open_store(s).meta.k
    assert _spec_of(s, f"levels/{k}") is not None
    assert _spec_of(s, "errors") is not None and _spec_of(s, "mask") is not None
    assert _spec_of(s, "levels/0") is None  # sharded
    meta = zarr.open_array(s, path=f"levels/{k}").metadata.to_dict()
    no_crc = dict(meta, codecs=list(meta["codecs"])[:2])
    assert chunkwrite.chunk_spec("x", no_crc) is None  # format 1: no checksum
    big_endian = {"name": "bytes", "configuration": {"endian": "big"}}
    big = dict(meta, codecs=[big_endian, *list(meta["codecs"])[1:]])
    assert chunkwrite.chunk_spec("x", big) is None
    grid = dict(meta["chunk_grid"], configuration={"chunk_shape": [2, 1, meta["shape"][2]]})
    assert chunkwrite.chunk_spec("x", dict(meta, chunk_grid=grid)) is None


def test_remote_targets_keep_zarrs_writer(monkeypatch, dem_factory, tmp_path):
    """A zarr Store object (not a local directory) is written through zarr: no direct write,
    and the store reads back right."""
    calls = []
    monkeypatch.setattr(chunkwrite, "write_local", lambda *a, **k: calls.append(a))
    data = fractal((70, 70), 2)
    store = zarr.storage.MemoryStore()
    tile(dem_factory(data), store, TileOptions(block_size=33))
    assert calls == []
    st = open_store(store)
    assert np.array_equal(st.read_block((0, 1)), data[:33, 32:65])
    # the last row and column of blocks are sparse (6 of 33 samples): their chosen frames are
    # put through the store too
    assert np.array_equal(st.read_block((2, 2), extent=st.block_extent((2, 2))), data[64:, 64:])


def test_a_failed_write_leaves_no_chunk(monkeypatch, tmp_path, dem_factory):
    """A write that fails before its rename leaves neither the chunk nor its temporary file."""
    tile(dem_factory(fractal((70, 70), 2)), tmp_path / "s.zarr", TileOptions(block_size=33))
    spec = _spec_of(tmp_path / "s.zarr", "errors")
    assert spec is not None

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        chunkwrite.write_local(str(tmp_path / "new"), spec, (0, 0), np.zeros(spec.shape))
    assert [p for p in (tmp_path / "new").rglob("*") if p.is_file()] == []
    with pytest.raises(ValueError, match="a block's chunk is"):
        chunkwrite.encode_chunk(np.zeros((3,)), spec)


@pytest.mark.parametrize(
    ("dtype", "bits"), [("uint8", True), ("int32", True), ("int16", False), (">u2", True)]
)
def test_single_chunk_is_zarrs_bytes(tmp_path, dtype, bits):
    """The index tables' one chunk (tiler.schema's layout): zarr's bytes for the same array,
    whatever the dtype, byte order or shuffle."""
    from tiler import schema

    values = (np.arange(33 * 17) * 7919 % 251).reshape(33, 17).astype(dtype)
    g = zarr.open_group(tmp_path / "t.zarr", mode="w")
    codecs = schema.codecs(2, 5, values.dtype.itemsize, bits, 4096)
    arr = g.create_array("t", data=values, chunks=values.shape, compressors=codecs)
    key, data = chunkwrite.single_chunk(values, arr.metadata.to_dict())
    assert key == "c/0/0"
    assert data == (tmp_path / "t.zarr" / "t" / "c" / "0" / "0").read_bytes()
    other = chunkwrite.single_chunk(values + 1, arr.metadata.to_dict())
    assert other is not None and other[1] != data  # the control: other values, other bytes


def test_single_chunk_only_where_it_applies(tmp_path):
    """None (zarr writes) for several chunks, no crc32c (format 1), other shapes or dtypes."""
    from tiler import schema

    g = zarr.open_group(tmp_path / "t.zarr", mode="w")
    v = np.zeros((8, 8), np.int32)
    chunked = g.create_array("a", shape=(8, 8), chunks=(4, 8), dtype="int32",
                             compressors=schema.codecs(2, 5, 4))  # fmt: skip
    v1 = g.create_array("b", shape=(8, 8), chunks=(8, 8), dtype="int32",
                        compressors=schema.codecs(1, 5, 4))  # fmt: skip
    ok = g.create_array("c", shape=(8, 8), chunks=(8, 8), dtype="int32",
                        compressors=schema.codecs(2, 5, 4))  # fmt: skip
    assert chunkwrite.single_chunk(v, chunked.metadata.to_dict()) is None
    assert chunkwrite.single_chunk(v, v1.metadata.to_dict()) is None
    assert chunkwrite.single_chunk(v[:4], ok.metadata.to_dict()) is None
    assert chunkwrite.single_chunk(v.astype(np.int64), ok.metadata.to_dict()) is None
    assert chunkwrite.single_chunk(v, ok.metadata.to_dict()) is not None
