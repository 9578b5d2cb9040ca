"""Is an array's zarr metadata what a format-2 store has? (pure: dicts and numpy)

zarr decodes whatever an array's ``zarr.json`` says: an edit that still parses — the ``bytes``
codec's endian, a codec removed, another chunk key separator, another data type or fill value —
makes every read of the array wrong with no error (a big-endian reading of levels, every chunk
"missing" and read as fill, a crc32c no longer checked). The chain of a format-2 store is fixed
(``docs/FORMAT.md``); :func:`array_problem` names the first departure from it. Compression
settings (blosc's cname, clevel, shuffle, blocksize, typesize) are not checked: blosc frames
describe themselves, and stores written with other settings decode the same.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tiler.layout import level_size
from tiler.schema import (
    INDEX_DTYPES,
    SHARDED_LEVELS,
    expected_table,
    index_chunk,
    level_fill,
)

_SEPARATOR = {"name": "default", "configuration": {"separator": "/"}}


def expected(name: str, meta: Any) -> tuple[str, Any, tuple[int, ...], tuple[int, ...] | None]:
    """``(data type, fill value, chunk shape, inner chunk shape or None)`` of array ``name``
    in a format-2 store described by ``meta`` (-1 in a chunk shape: any)."""
    rows, cols = meta.grid.shape
    side = meta.block_size
    if name.startswith("levels/"):
        i = int(name.split("/")[1])
        n = level_size(i)
        fill = int(level_fill(meta.storage_dtype))
        if i < SHARDED_LEVELS:  # (blocks a shard: 16², and other in stores tiled so in tests)
            return meta.storage_dtype, fill, (-1, -1, n), (1, 1, n)
        return meta.storage_dtype, fill, (1, 1, n), None
    if name == "errors":
        return "float16", math.nan, (1, 1, len(meta.error_fields), -1), None
    if name == "mask":
        return "bool", True, (1, 1, side, side), None
    if name == "index/window":
        return "int32", 0, (*index_chunk(rows, cols), 4), None
    if name == "index/content":
        return "uint64", 0, index_chunk(rows, cols), None
    if name.startswith("index/"):
        dt, fv = INDEX_DTYPES[name.split("/", 1)[1]]
        return dt, fv, index_chunk(rows, cols), None
    table = expected_table(name, meta.k)
    return str(table.dtype), 0, tuple(table.shape), None


def _chain_problem(codecs: list[dict], dtype: str, what: str) -> str | None:
    names = [c.get("name") for c in codecs]
    if names != ["bytes", "blosc", "crc32c"]:
        return f"{what}codecs {names}, not ['bytes', 'blosc', 'crc32c']"
    endian = (codecs[0].get("configuration") or {}).get("endian")
    if np.dtype(dtype).itemsize > 1 and endian != "little":
        return f"{what}bytes codec endian {endian!r}, not 'little'"
    return None


def _same_fill(got: Any, want: Any) -> bool:
    if isinstance(want, float) and math.isnan(want):
        return isinstance(got, str) and got == "NaN" or (isinstance(got, float) and math.isnan(got))
    if isinstance(want, bool) or isinstance(got, bool):
        return got is want or got == want and type(got) is type(want)
    return isinstance(got, int | float) and got == want


def array_problem(name: str, md: dict[str, Any], meta: Any) -> str | None:
    """Why array ``name``'s metadata ``md`` (``zarr.Array.metadata.to_dict()``) is not what a
    format-2 store described by ``meta`` holds, or None when it is."""
    dtype, fill, chunks, inner = expected(name, meta)
    got_dtype = str(md.get("data_type"))
    if got_dtype != dtype:
        return f"data type {got_dtype!r}, not {dtype!r}"
    if not _same_fill(md.get("fill_value"), fill):
        return f"fill value {md.get('fill_value')!r}, not {fill!r}"
    grid = (md.get("chunk_grid") or {}).get("configuration") or {}
    got_chunks = tuple(grid.get("chunk_shape") or ())
    if len(got_chunks) != len(chunks) or any(
        w != -1 and g != w for g, w in zip(got_chunks, chunks, strict=False)
    ):
        return f"chunk shape {list(got_chunks)}, not {[c for c in chunks]}"
    if md.get("chunk_key_encoding") != _SEPARATOR:
        return f"chunk key encoding {md.get('chunk_key_encoding')!r}, not {_SEPARATOR!r}"
    if md.get("storage_transformers"):
        return f"storage transformers {md.get('storage_transformers')!r}"
    codecs = list(md.get("codecs") or [])
    if inner is None:
        return _chain_problem(codecs, dtype, "")
    if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
        return f"codecs {[c.get('name') for c in codecs]}, not ['sharding_indexed']"
    cfg = codecs[0].get("configuration") or {}
    if tuple(cfg.get("chunk_shape") or ()) != inner:
        return f"inner chunk shape {cfg.get('chunk_shape')}, not {list(inner)}"
    why = _chain_problem(list(cfg.get("codecs") or []), dtype, "inner ")
    if why is not None:
        return why
    idx = list(cfg.get("index_codecs") or [])
    if [c.get("name") for c in idx] != ["bytes", "crc32c"] or (
        (idx[0].get("configuration") or {}).get("endian") != "little"
    ):
        return f"shard index codecs {idx!r}, not [bytes (little-endian), crc32c]"
    if cfg.get("index_location", "end") != "end":
        return f"shard index location {cfg.get('index_location')!r}, not 'end'"
    return None
