"""Direct writes of block chunks to a local format-2 store (no zarr call per chunk).

The writing twin of :mod:`tiler.chunkread`. A zarr ``Array.__setitem__`` of one block's chunk
costs ~1-2 ms of hops to zarr's event loop and thread pool on top of the codec; a 1025² block
writes 7 such chunks (levels 6..10, errors, mask). The arrays a block worker writes have one
codec chain, ``bytes`` (little endian) → ``blosc`` → ``crc32c``, with one chunk per block, so
the worker can encode the chunk itself with the same numcodecs blosc zarr calls and write the
file the way zarr's ``LocalStore`` does (a temporary file renamed over the key: a killed
writer never leaves half a chunk). The bytes are zarr's, bit for bit (tested);
:func:`chunk_spec` accepts an array only if its metadata is exactly that chain with one chunk
per block, and anything else keeps zarr's writer.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from dataclasses import dataclass
from typing import Any

import numpy as np

from tiler.chunkread import is_block_chain, regular_array

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

__all__ = ["ChunkSpec", "chunk_spec", "encode_chunk", "write_local"]


@dataclass(frozen=True)
class ChunkSpec:
    """How one block-chunked array's chunks are encoded (see the module doc)."""

    name: str
    shape: tuple[int, ...]  # a block's chunk, without the two block axes
    dtype: np.dtype  # little-endian
    codec: Any  # numcodecs Blosc configured as the array's blosc codec

    def key(self, block: tuple[int, int]) -> str:
        """Store key of ``block``'s chunk."""
        return f"{self.name}/c/{block[0]}/{block[1]}" + "/0" * len(self.shape)


def chunk_spec(name: str, metadata: dict[str, Any]) -> ChunkSpec | None:
    """The :class:`ChunkSpec` of an array from its zarr metadata (``to_dict()``), or None if
    its chunks are not stored the way this module encodes them (zarr then writes them)."""
    if google_crc32c is None or Blosc is None or not _TYPESIZE_PASSED:
        return None
    parsed = regular_array(metadata)
    if parsed is None:
        return None
    dtype, shape, chunks, codecs = parsed
    if (
        metadata.get("zarr_format") != 3
        or len(shape) < 3
        or chunks != (1, 1, *shape[2:])
        or not is_block_chain(codecs, dtype.itemsize)
    ):
        return None
    cfg = dict(codecs[1].get("configuration") or {})
    try:
        codec = Blosc(
            cname=str(cfg["cname"]),
            clevel=int(cfg["clevel"]),
            shuffle=_SHUFFLE[str(cfg["shuffle"])],
            blocksize=int(cfg.get("blocksize", 0)),
            typesize=int(cfg.get("typesize", dtype.itemsize)),
        )
    except (KeyError, TypeError, ValueError):
        return None
    return ChunkSpec(name, shape[2:], dtype, codec)


def _encode(values: np.ndarray, spec: ChunkSpec) -> tuple[Any, bytes]:
    """The blosc payload of a block's little-endian values and its crc32c (4 bytes)."""
    arr = np.asarray(values)
    if arr.shape != spec.shape:
        raise ValueError(f"{spec.name}: a block's chunk is {spec.shape}, got {arr.shape}")
    raw = np.ascontiguousarray(arr, dtype=spec.dtype).reshape(-1).view(np.uint8)
    payload = spec.codec.encode(raw)
    return payload, google_crc32c.value(payload).to_bytes(4, "little")


def encode_chunk(values: np.ndarray, spec: ChunkSpec) -> bytes:
    """A block's chunk bytes: blosc of its little-endian values, then their crc32c."""
    payload, crc = _encode(values, spec)
    return bytes(payload) + crc


def write_local(root: str, spec: ChunkSpec, block: tuple[int, int], values: np.ndarray) -> int:
    """Write ``block``'s chunk of ``spec``'s array under ``root`` (atomically: a temporary
    file renamed over the key, as zarr's ``LocalStore`` does); returns the bytes written."""
    payload, crc = _encode(values, spec)  # written as two pieces: no copy of the payload
    path = os.path.join(root, *spec.key(block).split("/"))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        with open(tmp, "wb") as f:
            n = f.write(payload) + f.write(crc)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return n
