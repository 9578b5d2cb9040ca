"""Direct reads of level chunks from a local format-2 store (no zarr call per chunk).

A zarr ``Array.__getitem__`` costs ~1-1.5 ms on a local disk whatever the chunk size (a
cross-thread hop to zarr's event loop, then thread-pool hops for the file read and the codec);
a 1025² block is 11 such calls. The level arrays have one fixed codec chain, so the reader can
decode the chunk files itself: ``bytes`` (little endian) → ``blosc`` → ``crc32c``, and for levels
``0..SHARDED_LEVELS-1`` the ``sharding_indexed`` codec (inner chunks with that chain, an index
of ``(offset, nbytes)`` uint64 pairs plus its own crc32c at the end of the shard). The format
is unchanged: :func:`level_spec` accepts an array only if its zarr metadata is exactly that
chain (anything else keeps zarr's reader), and every crc32c is checked as zarr checks it. The
per-block ``errors`` and ``mask`` arrays (one unsharded chunk per block, the same chain) are read
the same way (:func:`block_spec`), in their chunk's shape.

Pure functions here take bytes; :func:`read_local` is the only one touching files (a remote
store's chunks: :mod:`tiler.chunkread_remote`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

try:  # both are zarr's own dependencies (its crc32c and blosc codecs)
    import google_crc32c
    from numcodecs import blosc
except ImportError:  # pragma: no cover - zarr itself needs them
    google_crc32c = None
    blosc = None

EMPTY = np.uint64(2**64 - 1)  # the shard index's offset/nbytes of an absent inner chunk
_BYTES_LE = {"name": "bytes", "configuration": {"endian": "little"}}
_CRC = {"name": "crc32c"}


class ChecksumMismatch(ValueError):
    """A chunk's (or shard index's) stored crc32c differs from its content's."""


class ChunkDecodeError(ValueError):
    """A chunk that passed its checksum does not decode to the expected values."""


@dataclass(frozen=True)
class LevelSpec:
    """How one level array's block chunks are stored (see the module doc)."""

    name: str
    n: int  # values per block
    dtype: np.dtype  # little-endian storage dtype
    shard: tuple[int, int] | None  # blocks per shard (rows, cols), None if unsharded
    shape: tuple[int, ...] = ()  # a block's chunk shape past (1, 1); () means (n,)

    def key(self, block: tuple[int, int]) -> str:
        """Store key of the chunk (or shard) holding ``block``."""
        br, bc = block
        if self.shard is None:
            return f"{self.name}/c/{br}/{bc}" + "/0" * max(1, len(self.shape))
        return f"{self.name}/c/{br // self.shard[0]}/{bc // self.shard[1]}/0"

    def inner(self, block: tuple[int, int]) -> int:
        """Index of ``block``'s inner chunk in its shard (C order)."""
        assert self.shard is not None
        return (block[0] % self.shard[0]) * self.shard[1] + block[1] % self.shard[1]

    @property
    def index_nbytes(self) -> int:
        """Bytes of the encoded shard index (16 per inner chunk + the crc32c)."""
        assert self.shard is not None
        return 16 * self.shard[0] * self.shard[1] + 4


def is_block_chain(codecs: Any, itemsize: int) -> bool:
    """``[bytes little, blosc, crc32c]`` (any blosc settings: its frames describe themselves;
    one-byte types have no endianness, and zarr then writes ``bytes`` without one)."""
    c = list(codecs)
    return (
        len(c) == 3
        and (dict(c[0]) == _BYTES_LE or (itemsize == 1 and dict(c[0]) == {"name": "bytes"}))
        and dict(c[1]).get("name") == "blosc"
        and dict(c[2]) == _CRC
    )


def regular_array(
    metadata: dict[str, Any], separators: tuple[str, ...] = ("/",)
) -> tuple[np.dtype, tuple[int, ...], tuple[int, ...], list[Any]] | None:
    """``(little-endian dtype, shape, chunk shape, codecs)`` of an array's zarr metadata
    (``to_dict()``) if it has a regular chunk grid, default chunk keys with a separator in
    ``separators`` and no storage transformers (the layouts this module and
    :mod:`tiler.chunkwrite` address), else None. This module's keys (:meth:`LevelSpec.key`)
    are ``/``-separated: only a writer that builds its keys from the array's separator
    (:class:`tiler.chunkwrite.ChunkSpec`) passes ``("/", ".")``."""
    try:
        dtype = np.dtype(str(metadata["data_type"])).newbyteorder("<")
        shape = tuple(int(x) for x in metadata["shape"])
        grid = metadata["chunk_grid"]
        chunks = tuple(int(x) for x in grid["configuration"]["chunk_shape"])
        cke = metadata["chunk_key_encoding"]
        codecs = list(metadata["codecs"])
    except (KeyError, TypeError, ValueError):
        return None
    if (
        grid.get("name") != "regular"
        or cke.get("name") != "default"
        or dict(cke.get("configuration") or {}).get("separator", "/") not in separators
        or metadata.get("storage_transformers")
    ):
        return None
    return dtype, shape, chunks, codecs


def level_spec(name: str, metadata: dict[str, Any]) -> LevelSpec | None:
    """The :class:`LevelSpec` of a level array from its zarr metadata (``to_dict()``), or None
    if the array is not stored the way this module decodes (zarr then reads it)."""
    if google_crc32c is None or blosc is None or not hasattr(os, "pread"):  # else zarr reads
        return None
    parsed = regular_array(metadata)
    if parsed is None:
        return None
    dtype, shape, chunks, codecs = parsed
    if dtype.kind != "u" or len(shape) != 3 or len(chunks) != 3:
        return None
    n = shape[2]
    if is_block_chain(codecs, dtype.itemsize) and chunks == (1, 1, n):
        return LevelSpec(name, n, dtype, None)
    if len(codecs) != 1 or dict(codecs[0]).get("name") != "sharding_indexed":
        return None
    cfg = dict(codecs[0].get("configuration") or {})
    if (
        tuple(int(x) for x in cfg.get("chunk_shape", ())) != (1, 1, n)
        or not is_block_chain(cfg.get("codecs", ()), dtype.itemsize)
        or [dict(c) for c in cfg.get("index_codecs", ())] != [_BYTES_LE, _CRC]
        or cfg.get("index_location", "end") != "end"
        or chunks[2] != n
    ):
        return None
    return LevelSpec(name, n, dtype, (chunks[0], chunks[1]))


def block_spec(name: str, metadata: dict[str, Any]) -> LevelSpec | None:
    """The :class:`LevelSpec` of another per-block array (``errors``, ``mask``: one unsharded
    chunk ``(1, 1, ...)`` per block with the block chain), or None (zarr then reads it);
    :func:`read_local` returns its values in the chunk's shape."""
    if google_crc32c is None or blosc is None or not hasattr(os, "pread"):
        return None
    parsed = regular_array(metadata)
    if parsed is None:
        return None
    dtype, shape, chunks, codecs = parsed
    if len(shape) < 3 or chunks != (1, 1, *shape[2:]) or not is_block_chain(codecs, dtype.itemsize):
        return None
    return LevelSpec(name, int(np.prod(shape[2:])), dtype, None, tuple(shape[2:]))


def direct_specs(arrays: dict[str, Any], k: int) -> dict[str, LevelSpec]:
    """The :class:`LevelSpec` of every array of a ``k`` store read directly (levels
    ``0..k``, ``errors``, ``mask``; ``arrays``: the open zarr arrays by name), those whose
    metadata is the expected chain."""
    out = {}
    for name in [*(f"levels/{i}" for i in range(k + 1)), "errors", "mask"]:
        meta = arrays[name].metadata.to_dict()
        spec = level_spec(name, meta) if name.startswith("levels/") else block_spec(name, meta)
        if spec is not None:
            out[name] = spec
    return out


def check_crc(data: bytes, what: str) -> np.ndarray:
    """The payload of ``data`` (all but its trailing little-endian crc32c, as a uint8 view),
    checked."""
    if len(data) < 4:
        raise ChecksumMismatch(f"{what} is {len(data)} bytes: too short to hold its checksum")
    body = np.frombuffer(data, dtype=np.uint8)[:-4]
    stored = int.from_bytes(data[-4:], "little")
    computed = google_crc32c.value(body)
    if stored != computed:
        raise ChecksumMismatch(
            f"{what}: stored and computed checksum do not match "
            f"(stored {stored:#010x}, computed {computed:#010x})"
        )
    return body


def decode_chunk(data: bytes, spec: LevelSpec, out: np.ndarray | None = None) -> np.ndarray:
    """A block's stored values (``(n,)``) from its chunk bytes, decompressed into ``out``
    (contiguous, ``n`` values of the storage dtype) or a new array."""
    return decompress(check_chunk(data, spec), spec, out)


def check_chunk(data: bytes, spec: LevelSpec) -> np.ndarray:
    """The blosc frame of a chunk's bytes, its crc32c and frame size checked (what
    :func:`decompress` takes)."""
    body = check_crc(data, f"chunk of {spec.name}")
    want = spec.n * spec.dtype.itemsize
    # blosc 1 header: version, versionlz, flags, typesize, then uint32 LE nbytes, blocksize,
    # cbytes (c-blosc README_HEADER); checked so a short frame cannot half-fill ``out``
    nbytes, cbytes = _u32(data, 4), _u32(data, 12)
    if len(body) < 16 or cbytes != len(body) or nbytes != want:
        raise ChunkDecodeError(
            f"chunk of {spec.name} is not a blosc frame of {want} bytes ({spec.n} values): "
            f"header says {nbytes} bytes from {cbytes}, the chunk has {len(body)}"
        )
    return body


def decompress(body: np.ndarray, spec: LevelSpec, out: np.ndarray | None = None) -> np.ndarray:
    """A block's stored values (``(n,)``) from a checked blosc frame (:func:`check_chunk`),
    into ``out`` (see :func:`decode_chunk`) or a new array."""
    native = spec.dtype.isnative
    if out is None or not native:
        buf = np.empty(spec.n, dtype=spec.dtype)
    else:
        if out.shape != (spec.n,) or out.dtype != spec.dtype or not out.flags.c_contiguous:
            raise ValueError(f"out must be {spec.n} contiguous {spec.dtype} values")
        buf = out
    try:
        blosc.decompress(body, buf)
    except (RuntimeError, ValueError, TypeError) as exc:
        raise ChunkDecodeError(f"chunk of {spec.name} does not decompress: {exc}") from exc
    if native:
        return buf
    if out is None:  # pragma: no cover - big-endian hosts
        return buf.astype(spec.dtype.newbyteorder("="))
    out[...] = buf  # pragma: no cover
    return out


def _u32(data: bytes, at: int) -> int:
    return int.from_bytes(data[at : at + 4], "little")


def shard_entry(index: bytes, spec: LevelSpec, inner: int) -> tuple[int, int] | None:
    """``(offset, nbytes)`` of inner chunk ``inner`` from a shard's encoded index (checked),
    or None if the shard holds no such chunk."""
    body = check_crc(index, f"shard index of {spec.name}")
    if len(body) != spec.index_nbytes - 4:
        raise ChunkDecodeError(f"shard index of {spec.name} has {len(body)} bytes")
    pairs = np.frombuffer(body, dtype="<u8").reshape(-1, 2)
    off, nbytes = pairs[inner]
    if off == EMPTY and nbytes == EMPTY:
        return None
    return int(off), int(nbytes)


def read_local(
    root: str, spec: LevelSpec, block: tuple[int, int], out: np.ndarray | None = None
) -> np.ndarray | None:
    """``block``'s stored values of one level from a local store (into ``out`` if given, see
    :func:`decode_chunk`), or None if the store holds no such chunk."""
    path = os.path.join(root, *spec.key(block).split("/"))
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
    except (FileNotFoundError, NotADirectoryError):
        return None
    try:
        if spec.shard is None:
            values = decode_chunk(_read_all(fd), spec, out)
            return values.reshape(spec.shape) if len(spec.shape) > 1 else values
        size = os.fstat(fd).st_size
        want = spec.index_nbytes
        if size < want:
            raise ChunkDecodeError(f"shard of {spec.name} is {size} bytes, shorter than its index")
        entry = shard_entry(os.pread(fd, want, size - want), spec, spec.inner(block))
        if entry is None:
            return None
        off, nbytes = entry
        if off + nbytes > size - want:
            raise ChunkDecodeError(
                f"shard index of {spec.name} points past the chunk data ({off}+{nbytes} > "
                f"{size - want})"
            )
        return decode_chunk(os.pread(fd, nbytes, off), spec, out)
    finally:
        os.close(fd)


def _read_all(fd: int) -> bytes:
    size = os.fstat(fd).st_size
    parts, off = [], 0
    while off < size:
        chunk = os.pread(fd, size - off, off)
        if not chunk:  # the file shrank under us: decoding what is there fails its checksum
            break
        parts.append(chunk)
        off += len(chunk)
    return parts[0] if len(parts) == 1 else b"".join(parts)
