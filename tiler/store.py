"""The zarr v3 store: layout, metadata, writing helpers and the thread-safe reader.

Layout (see docs/FORMAT.md for the full description)::

    zarr.json                  root group; attribute "terrastream" holds the metadata
    levels/<i>                 (rows, cols, level_size(i)) stored level values, 1 chunk per block
    errors                     (rows, cols, 2, E) float16, monotone node errors (qiu, bound)
    mask                       (rows, cols, side, side) bool, True = valid (nodata blocks only)
    index/{exists,done,has_nodata,zmin,zmax,window,digest}   the grid index
    level_index, order_index   (side, side) the shared per-vertex level and order indices

The root attribute ``terrastream.complete`` is written last; a store without it is unfinished.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from tiler import static_error
from tiler.encoding import decode_grid, decode_levels, decode_next_level, dequantise
from tiler.errors import (
    StoreCorruptError,
    StoreError,
    StoreIncompleteError,
    StoreVersionError,
)
from tiler.grid import BlockGrid
from tiler.layout import grid_side, level_index, level_size, order_index
from tiler.vertical import from_metres, to_metres

FORMAT_VERSION = 1
ATTR = "terrastream"
SHARDED_LEVELS = 6  # levels 0..5 (<= 800 values a block) are sharded
SHARD_BLOCKS = 16  # blocks per shard edge for small levels
INDEX_CHUNK = 256
INDEX_NAMES = ("exists", "done", "has_nodata", "zmin", "zmax", "window", "digest")


def tool_version() -> str:
    """The installed terrastream version (or ``0+unknown`` when run from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("terrastream")
    except PackageNotFoundError:
        return "0+unknown"


def is_url(path: str | os.PathLike) -> bool:
    """True for fsspec URLs such as ``memory://``, ``http://``, ``s3://``."""
    return "://" in str(path)


@dataclass(frozen=True)
class StoreMeta:
    """The store's metadata (the root ``terrastream`` attribute)."""

    format_version: int
    k: int
    height: int
    width: int
    dtype: str  # source dtype (what read_block returns)
    storage_dtype: str
    encoding: str
    precision: float | None
    nodata: float | None
    crs_wkt: str | None
    geotransform: tuple[float, ...]  # GDAL order, of the source pixel corners
    vertical_units: str | None
    source: dict[str, Any]
    tool_version: str
    error_cap: int
    error_fields: tuple[str, ...]
    compressor: dict[str, Any]
    complete: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def value_dtype(self) -> np.dtype:
        """dtype of decoded level values (int32 for quantised stores, else the source dtype)."""
        return np.dtype("int32") if self.precision else np.dtype(self.dtype)

    @property
    def levels(self) -> int:
        """Number of levels per block (``k + 1``)."""
        return self.k + 1

    @property
    def block_size(self) -> int:
        """Block edge in samples."""
        return grid_side(self.k)

    @property
    def grid(self) -> BlockGrid:
        """The block grid with world coordinates of sample centres."""
        a, b, c, d, e, f = self.geotransform
        return BlockGrid(
            height=self.height,
            width=self.width,
            k=self.k,
            x0=c + a * 0.5 + b * 0.5,
            y0=f + d * 0.5 + e * 0.5,
            dx=abs(a),
            dy=abs(e),
        )

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict."""
        out = {k: v for k, v in self.__dict__.items() if k != "extra"}
        out["geotransform"] = list(self.geotransform)
        out["error_fields"] = list(self.error_fields)
        if self.nodata is not None and np.isnan(self.nodata):
            out["nodata"] = "NaN"  # JSON has no NaN
        out["levels"] = self.levels
        out["block_size"] = self.block_size
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> StoreMeta:
        """Parse (and validate) the root attribute."""
        try:
            version = int(d["format_version"])
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreCorruptError(f"store metadata has no valid format_version: {exc}") from exc
        if version > FORMAT_VERSION:
            raise StoreVersionError(
                f"store format version {version} is newer than this terrastream reads "
                f"({FORMAT_VERSION}); upgrade terrastream."
            )
        names = {f for f in cls.__dataclass_fields__ if f != "extra"}
        known = {k: v for k, v in d.items() if k in names}
        extra = {k: v for k, v in d.items() if k not in names and k not in ("levels", "block_size")}
        try:
            known["geotransform"] = tuple(float(x) for x in known["geotransform"])
            known["error_fields"] = tuple(known["error_fields"])
            if known.get("nodata") is not None:
                known["nodata"] = float(known["nodata"])
            return cls(**known, extra=extra)
        except (KeyError, TypeError, ValueError) as exc:
            raise StoreCorruptError(f"store metadata is incomplete or damaged: {exc}") from exc


DEFAULT_CLEVEL = 5


def compressor(level: int = DEFAULT_CLEVEL, typesize: int = 2, bits: bool = False) -> BloscCodec:
    """Blosc (zstd inside) with byte shuffle, or bit shuffle for index tables.

    Chosen by measurement (BENCHMARKS.md): on zigzagged residuals, byte shuffle + zstd beats
    plain zstd by 15-35 %; blosc is in the zarr v3 specification, unlike numcodecs filters.
    """
    return BloscCodec(
        cname="zstd",
        clevel=level,
        shuffle="bitshuffle" if bits else "shuffle",
        typesize=typesize,
        blocksize=0,
    )


def create_layout(group: zarr.Group, meta: StoreMeta, comp_level: int) -> None:
    """Create every array of an empty store (no data written)."""
    grid = meta.grid
    rows, cols = grid.shape
    side = grid.side
    itemsize = np.dtype(meta.storage_dtype).itemsize
    comp = [compressor(comp_level, itemsize)]
    for i in range(meta.levels):
        n = level_size(i)
        kw: dict[str, Any] = {}
        if i < SHARDED_LEVELS:
            kw["shards"] = (min(rows, SHARD_BLOCKS), min(cols, SHARD_BLOCKS), n)
        group.create_array(
            f"levels/{i}",
            shape=(rows, cols, n),
            chunks=(1, 1, n),
            dtype=meta.storage_dtype,
            compressors=comp,
            fill_value=0,
            dimension_names=("block_row", "block_col", f"value_{i}"),  # per-level lengths
            **kw,
        )
    e = sum(static_error.field_sizes(meta.k, meta.error_cap))
    group.create_array(
        "errors",
        shape=(rows, cols, len(meta.error_fields), e),
        chunks=(1, 1, len(meta.error_fields), e),
        dtype="float16",
        compressors=[compressor(comp_level, 2)],
        fill_value=0,
        dimension_names=("block_row", "block_col", "error_field", "error_value"),
    )
    group.create_array(
        "mask",
        shape=(rows, cols, side, side),
        chunks=(1, 1, side, side),
        dtype="bool",
        compressors=[compressor(comp_level, 1, bits=True)],
        fill_value=True,
        dimension_names=("block_row", "block_col", "row", "col"),
    )
    ic = (min(rows, INDEX_CHUNK), min(cols, INDEX_CHUNK))
    for name, dtype, fill in (
        ("exists", "bool", False),
        ("done", "bool", False),
        ("has_nodata", "bool", False),
        ("zmin", "float64", np.nan),
        ("zmax", "float64", np.nan),
        ("digest", "uint64", 0),
    ):
        group.create_array(
            f"index/{name}",
            shape=(rows, cols),
            chunks=ic,
            dtype=dtype,
            fill_value=fill,
            dimension_names=("block_row", "block_col"),
        )
    group.create_array(
        "index/window",
        shape=(rows, cols, 4),
        chunks=(*ic, 4),
        dtype="int32",
        fill_value=0,
        dimension_names=("block_row", "block_col", "row0_col0_rows_cols"),
    )
    for name, table in (("level_index", level_index(meta.k)), ("order_index", order_index(meta.k))):
        group.create_array(
            name,
            data=np.asarray(table),
            chunks=table.shape,  # one chunk: it compresses ~20x better than auto chunks
            compressors=[compressor(9, table.dtype.itemsize, bits=True)],
            dimension_names=("row", "col"),
        )


def write_meta(group: zarr.Group, meta: StoreMeta) -> None:
    """Write the root attribute (``complete`` as given in ``meta``)."""
    group.attrs[ATTR] = json.loads(json.dumps(meta.to_json(), allow_nan=False))


def read_meta(group: zarr.Group) -> StoreMeta:
    """Read and validate the root attribute."""
    d = group.attrs.get(ATTR)
    if not isinstance(d, dict):
        raise StoreCorruptError(
            "not a terrastream store: the root group has no 'terrastream' attribute"
        )
    return StoreMeta.from_json(d)


@dataclass(frozen=True)
class BlockIndex:
    """The grid index: per-block arrays of shape ``(rows, cols)`` (window: ``(rows, cols, 4)``)."""

    exists: np.ndarray
    done: np.ndarray
    has_nodata: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    window: np.ndarray
    digest: np.ndarray


class TerrainStore:
    """Read access to a finished store; safe to share between threads."""

    def __init__(self, url: str | os.PathLike, *, allow_incomplete: bool = False) -> None:
        self.url = str(url)
        try:
            self._group = zarr.open_group(self.url, mode="r")
        except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
            raise StoreError(f"no terrastream store at {self.url!r}: {exc}") from exc
        except (ValueError, KeyError, json.JSONDecodeError) as exc:
            raise StoreCorruptError(f"cannot open {self.url!r} as a zarr store: {exc}") from exc
        self.meta = read_meta(self._group)
        if not self.meta.complete and not allow_incomplete:
            raise StoreIncompleteError(
                f"store {self.url!r} was never finished (interrupted tiling?); run the same "
                "'terrastream tile' command again to complete it."
            )
        if np.dtype(self.meta.storage_dtype).kind != "u":
            raise StoreVersionError(
                f"store {self.url!r} was written by a pre-release terrastream (signed storage "
                f"dtype {self.meta.storage_dtype}); tile the DEM again"
            )
        self.grid = self.meta.grid
        self.k = self.meta.k
        self.dtype = np.dtype(self.meta.dtype)
        self._value_dtype = self.meta.value_dtype
        self._lock = threading.Lock()
        self._arrays: dict[str, zarr.Array] = {}

    def __repr__(self) -> str:
        m = self.meta
        return f"TerrainStore({self.url!r}, {m.height}x{m.width} {m.dtype}, k={m.k})"

    def _array(self, name: str) -> zarr.Array:
        with self._lock:
            arr = self._arrays.get(name)
            if arr is None:
                try:
                    arr = self._group[name]
                except KeyError as exc:
                    raise StoreCorruptError(f"store {self.url!r} has no array {name!r}") from exc
                self._arrays[name] = arr
            return arr

    @cached_property
    def index(self) -> BlockIndex:
        """The grid index (read once)."""
        return BlockIndex(**{n: self._array(f"index/{n}")[...] for n in INDEX_NAMES})

    def check_block(self, block: tuple[int, int]) -> tuple[int, int]:
        """Validate a block id and return it as ints."""
        br, bc = int(block[0]), int(block[1])
        self.grid.check_block(br, bc)
        return br, bc

    def read_level_raw(self, block: tuple[int, int], level: int) -> np.ndarray:
        """One block's one stored level, as stored (residuals): exactly one chunk read."""
        br, bc = self.check_block(block)
        if not 0 <= level <= self.k:
            raise StoreError(f"level {level} is outside 0..{self.k}")
        try:
            return self._array(f"levels/{level}")[br, bc]
        except (ValueError, OSError, RuntimeError) as exc:
            raise StoreCorruptError(
                f"cannot read level {level} of block {block} from {self.url!r}: {exc}"
            ) from exc

    def read_levels_raw(self, block: tuple[int, int], max_level: int) -> list[np.ndarray]:
        """Stored levels ``0..max_level`` of a block, read concurrently (one chunk each)."""
        import asyncio

        from zarr.core.sync import sync

        br, bc = self.check_block(block)
        if not 0 <= max_level <= self.k:
            raise StoreError(f"level {max_level} is outside 0..{self.k}")
        arrays = [self._array(f"levels/{i}").async_array for i in range(max_level + 1)]

        async def gather() -> list:
            return await asyncio.gather(*(a.getitem((br, bc)) for a in arrays))

        try:
            return [np.asarray(r) for r in sync(gather())]
        except (ValueError, OSError, RuntimeError) as exc:
            raise StoreCorruptError(
                f"cannot read levels 0..{max_level} of block {block} from {self.url!r}: {exc}"
            ) from exc

    def decode_next(self, levels: list[np.ndarray], raw: np.ndarray) -> np.ndarray:
        """Decode the next level from its raw values and the decoded levels ``0..L-1``
        (metres of a scaled store are taken back to its stored values first)."""
        levels = [from_metres(self.meta, v, self._value_dtype) for v in levels]  # tiler.vertical
        return decode_next_level(levels, raw, self._value_dtype)

    def to_heights(self, values: np.ndarray) -> np.ndarray:
        """Convert decoded storage values to the source dtype (dequantises ``--precision``);
        to float64 metres when the store records a band scale/offset or non-metre units."""
        if self.meta.precision:
            out = dequantise(values, self.meta.precision, self.dtype)
        else:
            out = values.astype(self.dtype, copy=False)
        return to_metres(self.meta, out)  # hook: tiler.vertical (identity for plain metres)

    def read_levels(self, block: tuple[int, int], max_level: int) -> list[np.ndarray]:
        """Decoded heights of levels ``0..max_level`` of a block (sequence order, source dtype)."""
        raws = self.read_levels_raw(block, max_level)
        return [self.to_heights(v) for v in decode_levels(raws, self._value_dtype)]

    def read_block(self, block: tuple[int, int], max_level: int | None = None) -> np.ndarray:
        """The ``2**L+1`` grid of a block at level ``L`` (default finest), in the source dtype."""
        level = self.k if max_level is None else int(max_level)
        if not 0 <= level <= self.k:
            raise StoreError(f"level {level} is outside 0..{self.k}")
        raws = self.read_levels_raw(block, level)
        return self.to_heights(decode_grid(raws, self._value_dtype, level))

    def read_mask(self, block: tuple[int, int]) -> np.ndarray:
        """``(side, side)`` bool, True where the block has terrain (not nodata, not padding)."""
        br, bc = self.check_block(block)
        return self._array("mask")[br, bc]

    def read_errors(self, block: tuple[int, int]) -> dict[str, list[np.ndarray]]:
        """The block's monotone error fields, unpacked per depth (see tiler.static_error)."""
        br, bc = self.check_block(block)
        packed = self._array("errors")[br, bc]
        return {
            name: static_error.unpack_field(packed[i], self.k, self.meta.error_cap)
            for i, name in enumerate(self.meta.error_fields)
        }

    def level_nbytes(self) -> list[int]:
        """Stored (compressed) bytes of each level array, summed over blocks."""
        return [_stored_bytes(self._group.store, f"levels/{i}") for i in range(self.k + 1)]

    def nbytes(self) -> dict[str, int]:
        """Stored bytes by component: levels, errors, mask, index, metadata, total."""
        store = self._group.store
        levels = sum(self.level_nbytes())
        parts = {
            "levels": levels,
            "errors": _stored_bytes(store, "errors"),
            "mask": _stored_bytes(store, "mask"),
            "index": _stored_bytes(store, "index")
            + _stored_bytes(store, "level_index")
            + _stored_bytes(store, "order_index"),
        }
        total = _stored_bytes(store, "")
        parts["metadata"] = total - sum(parts.values())
        parts["total"] = total
        return parts

    def blocks(self) -> Iterable[tuple[int, int]]:
        """Ids of blocks that hold terrain."""
        rr, cc = np.nonzero(self.index.exists)
        return list(zip(rr.tolist(), cc.tolist(), strict=True))


def _stored_bytes(store: Any, prefix: str) -> int:
    """Total size of the objects under ``prefix`` (a local directory or an fsspec store)."""
    import asyncio

    async def total() -> int:
        n = 0
        async for key in store.list_prefix(prefix):
            size = await store.getsize(key)
            n += int(size)
        return n

    from zarr.core.sync import sync

    try:
        return sync(total())
    except (NotImplementedError, asyncio.CancelledError, FileNotFoundError):
        return 0


def open_store(url: str | os.PathLike, *, allow_incomplete: bool = False) -> TerrainStore:
    """Open a finished store (local path or fsspec URL such as ``http://``, ``memory://``)."""
    if not is_url(url) and not os.path.exists(url):
        raise StoreError(f"no store at {str(url)!r}: the path does not exist")
    from tiler.remote import check_range_support

    check_range_support(str(url))  # hook: tiler.remote (HTTP servers must serve byte ranges)
    return TerrainStore(url, allow_incomplete=allow_incomplete)
