"""Sparse blocks (at most half terrain: padding past the DEM's edge, or nodata) write their
bit-shuffled level chunks byte shuffled where that frame is at most ``slack`` times as large
(``tiler.schema.sparse_byte_shuffle``): the rule as written, with the rule off as the control,
the same heights either way, and zarr reading the chunks too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from demtools import fractal
from numcodecs import blosc

from tiler import chunkwrite, schema, source
from tiler.assemble import block_params
from tiler.chunkread import check_crc
from tiler.store import open_store
from tiler.tile import TileOptions, tile

BIT, BYTE = 2, 1  # blosc's shuffle flags in a frame's header


def _smooth(shape: tuple[int, int]) -> np.ndarray:
    """Smooth int16 terrain: bit shuffle is much smaller on its full chunks (1.4x on level 7)."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (2000 + 800 * np.sin(x / 37.0) * np.cos(y / 53.0) + 0.5 * x).astype(np.int16)


def _frames(path: Path) -> dict[tuple[int, tuple[int, int]], tuple[int, np.ndarray]]:
    """``(level, block) -> (shuffle flag, stored values)`` of every bit-shuffled level chunk."""
    store = open_store(path)
    rows, cols = store.meta.grid.shape
    out = {}
    for lv in store.meta.compressor["bitshuffle_levels"]:
        for br in range(rows):
            for bc in range(cols):
                data = (path / "levels" / str(lv) / "c" / str(br) / str(bc) / "0").read_bytes()
                body = check_crc(data, "chunk")
                nbytes, _, _ = blosc._cbuffer_sizes(body)
                values = np.empty(nbytes // 2, np.uint16)
                blosc.decompress(body, values)
                out[lv, (br, bc)] = (blosc._cbuffer_metainfo(body)[1], values)
    return out


def _sparse(path: Path, block: tuple[int, int]) -> bool:
    mask = open_store(path).read_mask(block)
    return schema.is_sparse(int(mask.sum()), mask.size, schema.SPARSE_TERRAIN_MAX)


def _check_rule(path: Path) -> dict[str, int]:
    """Assert every bit-shuffled level chunk follows the rule; count the outcomes."""
    seen = {"full": 0, "sparse_byte": 0, "sparse_bit": 0}
    for (lv, block), (flag, values) in _frames(path).items():
        if not _sparse(path, block):
            assert flag == BIT, (lv, block)
            seen["full"] += 1
            continue
        spec = chunkwrite.chunk_spec(
            f"levels/{lv}", zarr.open_array(path, path=f"levels/{lv}").metadata.to_dict()
        )
        assert spec is not None and spec.byte_codec is not None
        bit, byte = len(spec.codec.encode(values)), len(spec.byte_codec.encode(values))
        keep = schema.keep_byte_frame(bit, byte, schema.SPARSE_BYTE_SLACK)
        assert flag == (BYTE if keep else BIT), (lv, block, bit, byte)
        seen["sparse_byte" if keep else "sparse_bit"] += 1
    return seen


def test_padded_blocks_follow_the_rule_both_ways(dem_factory, tmp_path):
    """Smooth terrain with padding (300x280 in 129² blocks: the last row and column of blocks
    are 19-34 % terrain): sparse chunks are byte shuffled where that is at most 5 % larger and
    stay bit shuffled where it is not (both happen here); full blocks stay bit shuffled."""
    src = dem_factory(_smooth((300, 280)))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=129, workers=1))
    seen = _check_rule(tmp_path / "s.zarr")
    assert seen["full"] > 0 and seen["sparse_byte"] > 0 and seen["sparse_bit"] > 0, seen
    rule = open_store(tmp_path / "s.zarr").meta.compressor["sparse_byte_shuffle"]
    assert rule == {"terrain_max": schema.SPARSE_TERRAIN_MAX, "slack": schema.SPARSE_BYTE_SLACK}


def test_rule_off_is_the_control_and_heights_are_the_same(monkeypatch, dem_factory, tmp_path):
    """With the rule off (a store that records none) every chunk is bit shuffled, so the byte
    frames above are the rule's doing; both stores give the same heights, through our reader
    and through zarr's."""
    data = fractal((300, 280), 2)
    src = dem_factory(data)
    tile(src, tmp_path / "on.zarr", TileOptions(block_size=129, workers=1))
    monkeypatch.setattr(source, "sparse_byte_shuffle", lambda encoding, k: None)
    tile(src, tmp_path / "off.zarr", TileOptions(block_size=129, workers=1))
    on, off = _frames(tmp_path / "on.zarr"), _frames(tmp_path / "off.zarr")
    assert on.keys() == off.keys()
    assert {flag for flag, _ in off.values()} == {BIT}
    assert sum(flag == BYTE for flag, _ in on.values()) >= 4  # fractal terrain: byte wins
    for key in on:
        assert np.array_equal(on[key][1], off[key][1]), key
    a, b = open_store(tmp_path / "on.zarr"), open_store(tmp_path / "off.zarr")
    assert "sparse_byte_shuffle" not in b.meta.compressor
    for block in [(r, c) for r in range(3) for c in range(3)]:
        ext = a.block_extent(block)
        assert np.array_equal(a.read_block(block, extent=ext), b.read_block(block, extent=ext))
    assert np.array_equal(a.read_block((2, 2), extent=a.block_extent((2, 2))), data[256:, 256:])
    k = a.meta.k
    via_zarr = zarr.open_array(tmp_path / "on.zarr", path=f"levels/{k}")[2, 2]
    assert np.array_equal(via_zarr, on[k, (2, 2)][1])


def test_nodata_makes_a_block_sparse(dem_factory, tmp_path):
    """No padding (257² in 129² blocks), one block three quarters nodata: only that block's
    chunks are byte shuffled."""
    data = fractal((257, 257), 3)
    data[128:, 128:224] = -9999
    src = dem_factory(data, nodata=-9999)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=129, workers=1))
    frames = _frames(tmp_path / "s.zarr")
    assert [key for key, (flag, _) in frames.items() if flag == BYTE]
    assert {block for (_, block), (flag, _) in frames.items() if flag == BYTE} == {(1, 1)}
    assert _sparse(tmp_path / "s.zarr", (1, 1)) and not _sparse(tmp_path / "s.zarr", (1, 0))
    _check_rule(tmp_path / "s.zarr")


def test_float_stores_record_no_rule(dem_factory, tmp_path):
    """A float XOR store bit shuffles no level, so it records no rule and writes none."""
    data = fractal((100, 90), 1).astype(np.float32) / 7
    tile(dem_factory(data), tmp_path / "f.zarr", TileOptions(block_size=65, workers=1))
    meta = open_store(tmp_path / "f.zarr").meta
    assert meta.compressor["bitshuffle_levels"] == []
    assert "sparse_byte_shuffle" not in meta.compressor
    assert block_params(meta).sparse_byte is None


@pytest.mark.parametrize(
    ("terrain", "samples", "want"),
    [(0, 100, True), (50, 100, True), (51, 100, False), (100, 100, False), (0, 0, False)],
)
def test_is_sparse_edges(terrain, samples, want):
    assert schema.is_sparse(terrain, samples, 0.5) is want


def test_keep_byte_frame_edges():
    assert schema.keep_byte_frame(100, 105, 1.05)
    assert not schema.keep_byte_frame(100, 106, 1.05)
    assert schema.keep_byte_frame(100, 50, 1.0) and not schema.keep_byte_frame(100, 101, 1.0)


def test_encode_sparse_picks_and_checksums(tmp_path, dem_factory):
    """``encode_sparse`` keeps the byte frame of mostly-zero residuals and the bit frame of
    smooth full ones, each with its crc32c; an array that is not bit shuffled is encoded
    as always."""
    tile(dem_factory(_smooth((300, 280))), tmp_path / "s.zarr", TileOptions(block_size=129))
    k = open_store(tmp_path / "s.zarr").meta.k
    meta = zarr.open_array(tmp_path / "s.zarr", path=f"levels/{k}").metadata.to_dict()
    spec = chunkwrite.chunk_spec(f"levels/{k}", meta)
    assert spec is not None
    full = _frames(tmp_path / "s.zarr")[k, (0, 0)][1]
    data, byte = chunkwrite.encode_sparse(full, spec, 1.05)
    assert not byte and data == chunkwrite.encode_chunk(full, spec)
    sparse = np.zeros_like(full)
    sparse[:200] = np.random.default_rng(0).integers(0, 40, 200)
    data, byte = chunkwrite.encode_sparse(sparse, spec, 1.05)
    assert byte and blosc._cbuffer_metainfo(check_crc(data, "chunk"))[1] == BYTE
    errors = chunkwrite.chunk_spec(
        "errors", zarr.open_array(tmp_path / "s.zarr", path="errors").metadata.to_dict()
    )
    assert errors is not None and errors.byte_codec is None
    e = np.zeros(errors.shape, np.float16)
    assert chunkwrite.encode_sparse(e, errors, 1.05) == (chunkwrite.encode_chunk(e, errors), False)
