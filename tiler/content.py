"""Content digests: what a block holds, tied to where it belongs (pure: numpy and hashlib).

A chunk's crc32c proves its bytes are the bytes written, not that they are this block's: a
valid chunk moved to another block's key, or copied from another store of the same shape,
passes it. Each block's content digest is computed when the block is encoded, from the block's
id, a digest of each stored level, of its error fields and of its mask, and its index row;
``index/content`` keeps it and ``verify`` recomputes it from what it reads (``docs/FORMAT.md``,
"Content digests").
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence

import google_crc32c  # (zarr's own dependency: its crc32c codec)
import numpy as np

#: the root metadata's ``extra`` key naming the scheme (absent: a store tiled before it)
CONTENT_KEY = "content_digests"
#: the scheme written now
CONTENT_SCHEME = "crc32c-fold-blake2b-64/v1"
#: the array holding them
CONTENT_ARRAY = "index/content"
#: the dtype each part is hashed in: errors are stored as float16, masks as bool
ERRORS_DTYPE = np.dtype("<f2")


def part_digest(values: np.ndarray | None, dtype: np.dtype | str) -> int:
    """A 64-bit digest of one stored array of a block (a level, the errors, the mask): the
    crc32c of its values in ``dtype`` (little-endian) in the high 32 bits, their count (mod
    2^32) in the low; 0 for ``None`` (a mask not stored: no nodata). crc32c runs at ~6 GB/s
    (blake2b at ~0.9 GB/s added 8 % to encoding a block); a misplaced chunk is not an
    adversary, and the block's digest hashes the parts with its id and index row."""
    if values is None:
        return 0
    dt = np.dtype(dtype).newbyteorder("<")
    a = np.ascontiguousarray(values, dtype=dt)
    crc = google_crc32c.value(a.tobytes())
    return (int(crc) << 32) | (a.size & 0xFFFFFFFF)


#: the fold of a block's part digests: ``acc = (acc * FOLD_PRIME + part) mod 2^64`` from
#: ``FOLD_SEED`` (FNV-1's constants), so a reader can fold them as it reads, one value a block
FOLD_SEED = 0xCBF29CE484222325
FOLD_PRIME = 0x100000001B3
_MASK = (1 << 64) - 1


def fold(acc: int, part: int) -> int:
    """``acc`` with one more part digest folded in."""
    return (int(acc) * FOLD_PRIME + int(part)) & _MASK


def fold_parts(parts: Sequence[int]) -> int:
    """The fold of ``parts`` (levels 0..k, errors, mask, in that order) from ``FOLD_SEED``."""
    acc = FOLD_SEED
    for p in parts:
        acc = fold(acc, p)
    return acc


def _finite_or_zero(v: float) -> tuple[float, int]:
    return (0.0, 1) if math.isnan(v) else (float(v), 0)


def content_digest(
    block: tuple[int, int],
    folded: int,
    exists: bool,
    has_nodata: bool,
    zmin: float,
    zmax: float,
    digest: int,
) -> int:
    """A block's content digest: its id, the :func:`fold_parts` of the :func:`part_digest` of
    each stored array (levels 0..k, errors, mask) and its index row (NaN heights hashed as a
    flag)."""
    lo, lo_nan = _finite_or_zero(zmin)
    hi, hi_nan = _finite_or_zero(zmax)
    h = hashlib.blake2b(digest_size=8)
    h.update(np.array([int(block[0]), int(block[1])], "<i8").tobytes())
    h.update(np.array([int(folded)], "<u8").tobytes())
    h.update(np.array([bool(exists), bool(has_nodata), lo_nan, hi_nan], "u1").tobytes())
    h.update(np.array([lo, hi], "<f8").tobytes())
    h.update(np.array([int(digest)], "<u8").tobytes())
    return int.from_bytes(h.digest(), "little")
