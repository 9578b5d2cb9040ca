"""Direct writes of block chunks to a local format-2 store (no zarr call per chunk).

The writing twin of :mod:`tiler.chunkread`. A zarr ``Array.__setitem__`` of one block's chunk
costs ~1-2 ms of hops to zarr's event loop and thread pool on top of the codec; a 1025² block
writes 7 such chunks (levels 6..10, errors, mask). The arrays a block worker writes have one
codec chain, ``bytes`` (little endian) → ``blosc`` → ``crc32c``, with one chunk per block, so
the worker can encode the chunk itself with the same numcodecs blosc zarr calls and write the
file the way zarr's ``LocalStore`` does (a temporary file renamed over the key: a killed
writer never leaves half a chunk). The bytes are zarr's, bit for bit (tested);
:func:`chunk_spec` accepts an array only if its metadata is exactly that chain with one chunk
per block, and anything else keeps zarr's writer. The ``journal`` (one ``uint8`` chunk per
block, the block's commit: :mod:`tiler.resume`) has that chain too, under ``.``-separated keys
(``journal/c.<r>.<c>.0``): a :class:`ChunkSpec` carries its array's key separator.

One choice is ours, not zarr's: a sparse block's bit-shuffled level chunk may be written byte
shuffled (:func:`encode_sparse`, the rule in :mod:`tiler.schema`). Blosc frames name their own
shuffle, so zarr and every blosc reader decode it; the block worker writes those bytes on every
path (direct, through the store for remote targets), so a store's bytes do not depend on it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from tiler.atomic import write_atomic
from tiler.chunkread import is_block_chain, regular_array
from tiler.schema import keep_byte_frame

try:  # zarr's own dependencies (its crc32c and blosc codecs)
    import google_crc32c
    from numcodecs import Blosc
except ImportError:  # pragma: no cover - zarr itself needs them
    google_crc32c = None
    Blosc = None


def _typesize_passed() -> bool:
    """zarr passes the blosc ``typesize`` to numcodecs from numcodecs 0.16 on (zarr's
    ``BloscCodec``); before that its bytes differ from these, so zarr writes."""
    try:
        import numcodecs
        from packaging.version import Version

        return Version(numcodecs.__version__) >= Version("0.16.0")
    except Exception:  # pragma: no cover - an unparsable version: leave it to zarr
        return False


_TYPESIZE_PASSED = _typesize_passed()
_SHUFFLE = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}
#: the chunk key separators of zarr's default key encoding (:meth:`ChunkSpec.key` builds both)
_SEPARATORS = ("/", ".")

__all__ = [
    "ChunkSpec",
    "chunk_spec",
    "encode_chunk",
    "encode_sparse",
    "single_chunk",
    "write_local",
    "write_local_bytes",
]


@dataclass(frozen=True)
class ChunkSpec:
    """How one block-chunked array's chunks are encoded (see the module doc)."""

    name: str
    shape: tuple[int, ...]  # a block's chunk, without the two block axes
    dtype: np.dtype  # little-endian
    codec: Any  # numcodecs Blosc configured as the array's blosc codec
    #: the same blosc with byte shuffle, for a bit-shuffled array (:func:`encode_sparse`)
    byte_codec: Any = None
    #: the array's chunk key separator (zarr's default encoding: ``/`` or ``.``)
    separator: str = "/"

    def key(self, block: tuple[int, int]) -> str:
        """Store key of ``block``'s chunk (``name/c/r/c/0`` or, for ``.``, ``name/c.r.c.0``)."""
        parts = ["c", str(block[0]), str(block[1]), *("0" * len(self.shape))]
        return f"{self.name}/{self.separator.join(parts)}"


def _chain(
    metadata: dict[str, Any], separators: tuple[str, ...] = ("/",)
) -> tuple[np.dtype, tuple, tuple, dict, int] | None:
    """``(little-endian dtype, shape, chunk shape, Blosc keywords but shuffle, shuffle)`` of a
    zarr v3 array with a regular grid, a chunk key separator in ``separators`` and this
    module's codec chain, else None."""
    if google_crc32c is None or Blosc is None or not _TYPESIZE_PASSED:
        return None
    parsed = regular_array(metadata, separators)
    if parsed is None:
        return None
    dtype, shape, chunks, codecs = parsed
    if metadata.get("zarr_format") != 3 or not is_block_chain(codecs, dtype.itemsize):
        return None
    cfg = dict(codecs[1].get("configuration") or {})
    try:
        kw = dict(
            cname=str(cfg["cname"]),
            clevel=int(cfg["clevel"]),
            blocksize=int(cfg.get("blocksize", 0)),
            typesize=int(cfg.get("typesize", dtype.itemsize)),
        )
        shuffle = _SHUFFLE[str(cfg["shuffle"])]
    except (KeyError, TypeError, ValueError):
        return None
    return dtype, shape, chunks, kw, shuffle


def chunk_spec(name: str, metadata: dict[str, Any]) -> ChunkSpec | None:
    """The :class:`ChunkSpec` of an array from its zarr metadata (``to_dict()``), or None if
    its chunks are not stored the way this module encodes them (zarr then writes them). Keys
    separated by ``/`` or ``.`` (the journal's) are both written: :meth:`ChunkSpec.key`."""
    parsed = _chain(metadata, _SEPARATORS)
    if parsed is None:
        return None
    dtype, shape, chunks, kw, shuffle = parsed
    if len(shape) < 3 or chunks != (1, 1, *shape[2:]):
        return None
    codec = Blosc(shuffle=shuffle, **kw)
    byte_codec = Blosc(shuffle=Blosc.SHUFFLE, **kw) if shuffle == Blosc.BITSHUFFLE else None
    cke = dict(metadata["chunk_key_encoding"].get("configuration") or {})
    return ChunkSpec(name, shape[2:], dtype, codec, byte_codec, str(cke.get("separator", "/")))


def single_chunk(values: np.ndarray, metadata: dict[str, Any]) -> tuple[str, bytes] | None:
    """The key (relative to the array) and zarr's bytes of the only chunk of an array stored
    in one chunk with this module's codec chain (``bytes`` → ``blosc`` → ``crc32c``), holding
    ``values``; None if the array is not stored that way (zarr then writes it). The store's
    two index tables (:func:`tiler.schema.create_layout`)."""
    parsed = _chain(metadata)
    if parsed is None:
        return None
    dtype, shape, chunks, kw, shuffle = parsed
    arr = np.asarray(values)
    if chunks != shape or arr.shape != shape or arr.dtype.newbyteorder("<") != dtype:
        return None
    raw = np.ascontiguousarray(arr, dtype=dtype).reshape(-1).view(np.uint8)
    payload = Blosc(shuffle=shuffle, **kw).encode(raw)
    return "c/" + "/".join("0" * len(shape)), bytes(payload) + _crc(payload)


def _raw(values: np.ndarray, spec: ChunkSpec) -> np.ndarray:
    arr = np.asarray(values)
    if arr.shape != spec.shape:
        raise ValueError(f"{spec.name}: a block's chunk is {spec.shape}, got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=spec.dtype).reshape(-1).view(np.uint8)


def _crc(payload: Any) -> bytes:
    return google_crc32c.value(payload).to_bytes(4, "little")


def _encode(values: np.ndarray, spec: ChunkSpec) -> tuple[Any, bytes]:
    """The blosc payload of a block's little-endian values and its crc32c (4 bytes)."""
    payload = spec.codec.encode(_raw(values, spec))
    return payload, _crc(payload)


def encode_chunk(values: np.ndarray, spec: ChunkSpec) -> bytes:
    """A block's chunk bytes: blosc of its little-endian values, then their crc32c."""
    payload, crc = _encode(values, spec)
    return bytes(payload) + crc


def encode_sparse(values: np.ndarray, spec: ChunkSpec, slack: float) -> tuple[bytes, bool]:
    """A sparse block's chunk bytes and whether they are the byte-shuffled frame: both frames
    of a bit-shuffled array are made and the byte-shuffled one kept when it is at most
    ``slack`` times the other's size (:func:`tiler.schema.keep_byte_frame`); else, and for an
    array that is not bit shuffled, :func:`encode_chunk`'s bytes."""
    if spec.byte_codec is None:
        return encode_chunk(values, spec), False
    raw = _raw(values, spec)
    bit, byte = spec.codec.encode(raw), spec.byte_codec.encode(raw)
    keep = keep_byte_frame(len(bit), len(byte), slack)
    payload = byte if keep else bit
    return bytes(payload) + _crc(payload), keep


def _write_file(root: str, spec: ChunkSpec, block: tuple[int, int], *pieces: Any) -> int:
    return write_atomic(os.path.join(root, *spec.key(block).split("/")), *pieces)


def write_local(root: str, spec: ChunkSpec, block: tuple[int, int], values: np.ndarray) -> int:
    """Write ``block``'s chunk of ``spec``'s array under ``root`` (atomically: a temporary
    file renamed over the key, as zarr's ``LocalStore`` does); returns the bytes written."""
    payload, crc = _encode(values, spec)  # written as two pieces: no copy of the payload
    return _write_file(root, spec, block, payload, crc)


def write_local_bytes(root: str, spec: ChunkSpec, block: tuple[int, int], data: bytes) -> int:
    """Write already encoded chunk bytes (:func:`encode_sparse`) the way :func:`write_local`
    does; returns the bytes written."""
    return _write_file(root, spec, block, data)
