"""The store's arrays: names, codecs (checksummed), fill values, chunk keys; creating the layout.

Format 2 puts the zarr v3 ``crc32c`` codec last in every array's codec chain (inside the shards
too, whose index carries its own crc32c), writes every chunk (``write_empty_chunks``) and uses a
fill value no written chunk holds (levels: the storage dtype's maximum; errors: NaN), so a chunk
read back as the fill value is a *missing* chunk, never silently zeros.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec

from tiler import static_error
from tiler.atomic import write_atomic
from tiler.content import CONTENT_KEY
from tiler.layout import level_index, level_size, order_index

FORMAT_VERSION = 2
ATTR = "terrastream"
SHARDED_LEVELS = 6  # levels 0..5 (<= 800 values a block) are sharded
SHARD_BLOCKS = 16  # blocks per shard edge for small levels
INDEX_CHUNK = 256
INDEX_NAMES = ("exists", "done", "has_nodata", "zmin", "zmax", "window", "digest")
# The level/order index tables: blosc clevel 9 is zstd's ultra level 22, which took 2.0-3.4 s for
# k = 10's order table (15.8 s for k = 11) on every tiling run; clevel 5 with whole power-of-two
# blocks (``table_blocksize``) makes it 44 KiB in ~17 ms. Measured in BENCHMARKS.md "Tiling".
TABLE_CLEVEL = 5
DEFAULT_CLEVEL = 3  # zstd 3 with 1 MiB blosc blocks: the size of zstd 5 in 1/3 the time
LEVEL_BLOCKSIZE = 1 << 20  # blosc block of the level arrays: one per chunk up to k = 10
WRITE_CONFIG = {"write_empty_chunks": True}
INDEX_DTYPES = {
    "exists": ("bool", False),
    "done": ("bool", False),
    "has_nodata": ("bool", False),
    "zmin": ("float64", np.nan),
    "zmax": ("float64", np.nan),
    "digest": ("uint64", 0),
}


def index_dtypes(meta: Any) -> dict[str, tuple[str, Any]]:
    """:data:`INDEX_DTYPES` of a store described by ``meta``, with ``content``
    (``index/content``, :mod:`tiler.content`) when the store keeps content digests."""
    out = dict(INDEX_DTYPES)
    if (getattr(meta, "extra", None) or {}).get(CONTENT_KEY):
        out["content"] = ("uint64", 0)
    return out


def compressor(
    level: int = DEFAULT_CLEVEL, typesize: int = 2, bits: bool = False, blocksize: int | None = None
) -> BloscCodec:
    """Blosc (zstd inside) with byte shuffle, or bit shuffle (``bits``); ``blocksize`` defaults
    to 1 MiB for byte shuffle and blosc's automatic blocks for bit shuffle.

    Chosen by measurement (``bench/codecs.py``, BENCHMARKS.md): on zigzagged residuals, byte
    shuffle + zstd beats plain zstd by 15-35 % and lz4/lz4hc are 12-28 % larger; zstd 3 with
    1 MiB blosc blocks (one block per chunk) is 0.996x the size of zstd 5 with automatic
    blocks and compresses in 0.32x the time. Blosc is in the zarr v3 specification.
    """
    if blocksize is None:
        blocksize = 0 if bits else LEVEL_BLOCKSIZE
    return BloscCodec(
        cname="zstd",
        clevel=level,
        shuffle="bitshuffle" if bits else "shuffle",
        typesize=typesize,
        blocksize=blocksize,
    )


COMPRESSOR_NAME = "blosc-zstd-shuffle"  # ``meta.compressor["name"]``
BIT_SHUFFLED_FINEST = 2  # integer stores bit shuffle their two finest levels (spacing 1-2 samples)


def bitshuffle_levels(encoding: str, k: int) -> list[int]:
    """The levels a new store bit shuffles (``meta.compressor["bitshuffle_levels"]``): the two
    finest of an integer-residual store, whose residuals over 1-2 samples have mostly zero high
    bits; none of a float-XOR store. Measured per level on real chunks (BENCHMARKS.md "Codec
    choice"): the finest levels 0.91-0.96x, the coarser ones and float XORs up to 1.11x, and
    bit-shuffled coarse levels decode up to 2x slower."""
    if encoding == "float-xor":
        return []
    return list(range(max(0, k + 1 - BIT_SHUFFLED_FINEST), k + 1))


#: Sparse blocks: a block at most this fraction terrain (the rest padding past the DEM's edge
#: or nodata, whose residuals are 0) has its bit-shuffled level chunks written byte shuffled when
#: that frame is at most ``SPARSE_BYTE_SLACK`` times the bit-shuffled one's bytes. Bit unshuffle
#: costs the whole 1025² chunk however little of it is terrain; byte unshuffle decodes such a
#: chunk in 0.39-0.62x the time (N44W072's edge blocks: +0.8-3.4 % bytes on level 10, 3-14 %
#: fewer on level 9; the smooth 4097² synthetic's level 10 +11-37 %, so there bit shuffle
#: stays). Measured by bench/level_codecs.py (BENCHMARKS.md "Tiling"); blosc frames name their
#: own shuffle, so every reader decodes both.
SPARSE_TERRAIN_MAX = 0.5
SPARSE_BYTE_SLACK = 1.05


def sparse_byte_shuffle(encoding: str, k: int) -> dict[str, float] | None:
    """The sparse-block rule a new store records (``meta.compressor["sparse_byte_shuffle"]``),
    or None where it bit shuffles no level (float XOR stores)."""
    if not bitshuffle_levels(encoding, k):
        return None
    return {"terrain_max": SPARSE_TERRAIN_MAX, "slack": SPARSE_BYTE_SLACK}


def is_sparse(terrain: int, samples: int, terrain_max: float) -> bool:
    """Whether a block with ``terrain`` of its ``samples`` terrain is sparse (at most
    ``terrain_max`` of it)."""
    return samples > 0 and terrain <= terrain_max * samples


def keep_byte_frame(bit_bytes: int, byte_bytes: int, slack: float) -> bool:
    """Whether a sparse block's chunk keeps its byte-shuffled frame (``byte_bytes``) over the
    bit-shuffled one (``bit_bytes``): at most ``slack`` times its size."""
    return byte_bytes <= slack * bit_bytes


def level_bits(compressor: dict[str, Any], level: int) -> bool:
    """Whether ``level``'s array is bit shuffled, from ``meta.compressor`` (stores written
    before the choice name no levels: all byte shuffled)."""
    return level in (compressor.get("bitshuffle_levels") or ())


def codecs(
    format_version: int, level: int, typesize: int, bits: bool = False, blocksize: int | None = None
) -> list[Any]:
    """The bytes-to-bytes codecs of an array: blosc, then crc32c from format 2 on."""
    out: list[Any] = [compressor(level, typesize, bits, blocksize)]
    if format_version >= 2:
        out.append(Crc32cCodec())
    return out


TABLE_MAX_BLOCK = 1 << 23


def table_blocksize(nbytes: int) -> int:
    """Blosc block of an index table: the largest power of two <= its bytes, at most 8 MiB.

    Bit shuffle applies to whole blocks, so a table in one block that is not a multiple of 8
    values compressed 16x worse (k = 8). Larger blocks compress the order table better: k = 10
    45,070 B in 4 MiB blocks (51,667 in 2 MiB, 76,964 automatic; 17 vs 10 ms), k = 11 116 KiB
    in 8 MiB (145 KiB in 2 MiB, the same time)."""
    return min(TABLE_MAX_BLOCK, 1 << (max(int(nbytes), 1).bit_length() - 1))


@contextmanager
def compact_metadata() -> Iterator[None]:
    """Write zarr metadata (``zarr.json``) without indentation inside the block: 8 KiB less
    per ``k = 10`` store (2 % of a 1201² SRTM tile's), the same JSON to every reader."""
    with zarr.config.set({"json_indent": None}):
        yield


def level_fill(storage_dtype: str | np.dtype) -> int:
    """Fill value of the level arrays: the storage dtype's maximum (never a whole written chunk)."""
    return int(np.iinfo(np.dtype(storage_dtype)).max)


def shard_shape(rows: int, cols: int) -> tuple[int, int]:
    """Blocks per shard of the small levels (rows, cols)."""
    return min(rows, SHARD_BLOCKS), min(cols, SHARD_BLOCKS)


def index_chunk(rows: int, cols: int) -> tuple[int, int]:
    """Blocks per chunk of the index arrays (rows, cols)."""
    return min(rows, INDEX_CHUNK), min(cols, INDEX_CHUNK)


def array_names(k: int) -> list[str]:
    """Every array of a store with ``k + 1`` levels."""
    names = [f"levels/{i}" for i in range(k + 1)]
    names += ["errors", "mask", *[f"index/{n}" for n in INDEX_NAMES], "level_index", "order_index"]
    return names


def chunk_key(name: str, block: tuple[int, int], rows: int, cols: int) -> str:
    """The store key of the chunk (or shard) holding ``block``'s data in array ``name``."""
    br, bc = block
    if name.startswith("levels/"):
        if int(name.split("/")[1]) < SHARDED_LEVELS:
            sr, sc = shard_shape(rows, cols)
            return f"{name}/c/{br // sr}/{bc // sc}/0"
        return f"{name}/c/{br}/{bc}/0"
    if name in ("errors", "mask"):
        return f"{name}/c/{br}/{bc}/0/0"
    if name.startswith("index/"):
        ir, ic = index_chunk(rows, cols)
        tail = "/0" if name == "index/window" else ""
        return f"{name}/c/{br // ir}/{bc // ic}{tail}"
    return f"{name}/c/0/0"


def layout_specs(meta: Any, comp_level: int) -> list[tuple[str, dict[str, Any]]]:
    """``(path, zarr create_array keywords)`` of every array of an empty store described by
    ``meta`` (only the level and order index tables carry data)."""
    v = meta.format_version
    grid = meta.grid
    rows, cols = grid.shape
    side = grid.side
    itemsize = np.dtype(meta.storage_dtype).itemsize
    fill = level_fill(meta.storage_dtype) if v >= 2 else 0
    cfg = WRITE_CONFIG if v >= 2 else None
    specs: list[tuple[str, dict[str, Any]]] = []
    for i in range(meta.levels):
        n = level_size(i)
        kw: dict[str, Any] = {}
        if i < SHARDED_LEVELS:
            kw["shards"] = (*shard_shape(rows, cols), n)
        specs.append(
            (
                f"levels/{i}",
                dict(
                    shape=(rows, cols, n),
                    chunks=(1, 1, n),
                    dtype=meta.storage_dtype,
                    compressors=codecs(
                        v,
                        comp_level,
                        itemsize,
                        level_bits(meta.compressor, i),
                        LEVEL_BLOCKSIZE,
                    ),
                    fill_value=fill,
                    dimension_names=("block_row", "block_col", f"value_{i}"),  # per-level lengths
                    config=cfg,
                    **kw,
                ),
            )
        )
    e = sum(static_error.field_sizes(meta.k, meta.error_cap))
    specs.append(
        (
            "errors",
            dict(
                shape=(rows, cols, len(meta.error_fields), e),
                chunks=(1, 1, len(meta.error_fields), e),
                dtype="float16",
                compressors=codecs(v, comp_level, 2),
                fill_value=np.nan if v >= 2 else 0,
                dimension_names=("block_row", "block_col", "field", "node"),
                config=cfg,
            ),
        )
    )
    specs.append(
        (
            "mask",
            dict(
                shape=(rows, cols, side, side),
                chunks=(1, 1, side, side),
                dtype="bool",
                compressors=codecs(v, comp_level, 1, bits=True),
                fill_value=True,
                dimension_names=("block_row", "block_col", "row", "col"),
            ),
        )
    )
    ic = index_chunk(rows, cols)
    for name, (dtype, fv) in index_dtypes(meta).items():
        specs.append(
            (
                f"index/{name}",
                dict(
                    shape=(rows, cols),
                    chunks=ic,
                    dtype=dtype,
                    fill_value=fv,
                    compressors=(
                        codecs(v, comp_level, np.dtype(dtype).itemsize) if v >= 2 else "auto"
                    ),
                    dimension_names=("block_row", "block_col"),
                    config=cfg,
                ),
            )
        )
    specs.append(
        (
            "index/window",
            dict(
                shape=(rows, cols, 4),
                chunks=(*ic, 4),
                dtype="int32",
                fill_value=0,
                compressors=codecs(v, comp_level, 4) if v >= 2 else "auto",
                dimension_names=("block_row", "block_col", "field"),
                config=cfg,
            ),
        )
    )
    for name, table in (("level_index", level_index(meta.k)), ("order_index", order_index(meta.k))):
        specs.append(
            (
                name,
                dict(
                    data=np.asarray(table),
                    chunks=table.shape,  # one chunk: it compresses ~20x better than auto chunks
                    compressors=codecs(
                        v, TABLE_CLEVEL, table.dtype.itemsize, True, table_blocksize(table.nbytes)
                    ),
                    dimension_names=("row", "col"),
                ),
            )
        )
    return specs


LAYOUT_METHODS = ("memory", "sequential", "concurrent")


def _documents(specs: list[tuple[str, dict[str, Any]]]) -> dict[str, bytes]:
    """Every key the arrays of ``specs`` write below the root group, with zarr's own bytes:
    the arrays' and their parent groups' ``zarr.json`` and the index tables' chunks, made by
    zarr in a ``MemoryStore`` (no store round trip per array; the root's own ``zarr.json`` is
    left out)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync
    from zarr.storage import MemoryStore

    from tiler.chunkwrite import single_chunk  # (it imports this module)

    mem = MemoryStore()
    root = zarr.open_group(mem, mode="w")
    chunks: dict[str, bytes] = {}
    for name, kw in specs:
        data = kw.get("data")
        if data is None:
            root.create_array(name, **kw)
            continue
        # an index table: its one chunk encoded here, the bytes zarr writes (~9 ms less than
        # zarr's write of these 1-4 MiB arrays for k = 10); a table not stored that way, zarr
        # writes. (Encoding them on a thread meanwhile gained nothing measurable.)
        rest = {key: v for key, v in kw.items() if key != "data"}
        arr = root.create_array(name, shape=data.shape, dtype=data.dtype, **rest)
        chunk = single_chunk(data, arr.metadata.to_dict())
        if chunk is None:
            arr[...] = data
        else:
            chunks[f"{name}/{chunk[0]}"] = chunk[1]

    async def items() -> dict[str, bytes]:
        proto = default_buffer_prototype()
        out = {}
        async for key in mem.list():
            buf = await mem.get(key, proto) if key != "zarr.json" else None
            if buf is not None:
                out[key] = buf.to_bytes()
        return out | chunks

    return sync(items())


def _write_documents(group: zarr.Group, docs: dict[str, bytes], arrays: list[str]) -> None:
    """Write ``docs`` (keys relative to ``group``) to the group's store: a local directory by
    plain file writes (:func:`tiler.atomic.write_atomic`), any other store in one gather of
    ``set`` calls. Refuses, before writing anything, if one of ``arrays`` exists already (as
    zarr's ``create_array`` does)."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync
    from zarr.errors import ContainsArrayError
    from zarr.storage import LocalStore

    store, prefix = group.store, f"{group.path}/" if group.path else ""
    if store.read_only:
        raise ValueError(f"cannot create a layout in the read-only store {store}")
    if isinstance(store, LocalStore):
        base = os.path.join(str(store.root), group.path)
        for name in arrays:
            if os.path.exists(os.path.join(base, name, "zarr.json")):
                raise ContainsArrayError(str(store), prefix + name)
        for key, data in docs.items():
            write_atomic(os.path.join(base, key), data)
        return

    async def put_all() -> None:
        found = await asyncio.gather(*(store.exists(f"{prefix}{n}/zarr.json") for n in arrays))
        for name, there in zip(arrays, found, strict=True):
            if there:
                raise ContainsArrayError(str(store), prefix + name)
        buf = default_buffer_prototype().buffer
        await asyncio.gather(*(store.set(prefix + k, buf.from_bytes(v)) for k, v in docs.items()))

    sync(put_all())


def create_layout(group: zarr.Group, meta: Any, comp_level: int, *, method: str = "memory") -> None:
    """Create every array of an empty store (no data written but the two index tables).

    ``method``: ``"memory"`` (default) has zarr build every document in memory
    (``_documents``) and writes them to the group's store at once; ``"sequential"``
    creates the arrays through the store one after another (the reference: ~2 ms of zarr's
    store round trips per array on a local disk, 23 arrays for ``k = 10``); ``"concurrent"``
    issues those creations all at once on zarr's event loop. The three write the same bytes
    (tested); ``"concurrent"`` is not the default because it changed the cold start the README
    example's stall control relies on (CHANGELOG.md)."""
    if method not in LAYOUT_METHODS:
        raise ValueError(f"method={method!r}: use one of {', '.join(LAYOUT_METHODS)}")
    specs = layout_specs(meta, comp_level)
    if method == "memory":
        _write_documents(group, _documents(specs), [n for n, _ in specs])
        return
    if method == "sequential":
        for name, kw in specs:
            group.create_array(name, **kw)
        return
    from zarr.api.asynchronous import open_group
    from zarr.core.sync import sync  # the loop zarr's synchronous API runs its stores on

    async def create_all() -> None:
        ag = await open_group(store=group.store, path=group.path, mode="r+")
        await asyncio.gather(*(ag.create_array(name, **kw) for name, kw in specs))

    sync(create_all())


def expected_table(name: str, k: int) -> np.ndarray:
    """The content ``level_index`` or ``order_index`` must have."""
    return level_index(k) if name == "level_index" else order_index(k)
