"""Helpers for store tests: comparing two stores byte for byte, damaging chunks on purpose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tiler.schema import ATTR

#: differ between two builds by design: the build's id (reader change detection), a repair's
#: revision (the same) and the root metadata's checksum, which covers them
VOLATILE = ("generation", "revision", "metadata_checksum")


def store_files(root: Path) -> dict[str, bytes]:
    """Every file of a local store by relative path (the root zarr.json normalised)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            rel = p.relative_to(root).as_posix()
            data = p.read_bytes()
            if rel == "zarr.json":
                doc = json.loads(data)
                for key in VOLATILE:
                    doc["attributes"][ATTR].pop(key, None)
                data = json.dumps(doc, sort_keys=True).encode()
            out[rel] = data
    return out


def diff_stores(a: Path, b: Path) -> list[str]:
    """Relative paths that differ between two local stores (empty: byte-identical)."""
    fa, fb = store_files(a), store_files(b)
    return sorted(k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k))


def chunk_files(root: Path, array: str) -> list[Path]:
    """The chunk files of one array of a local store."""
    base = root / array / "c"
    return sorted(p for p in base.rglob("*") if p.is_file()) if base.exists() else []


def flip_bit(path: Path, rng: np.random.Generator) -> tuple[int, int]:
    """Flip one random bit of a file; returns (byte offset, bit)."""
    data = bytearray(path.read_bytes())
    off = int(rng.integers(0, len(data)))
    bit = int(rng.integers(0, 8))
    data[off] ^= 1 << bit
    path.write_bytes(bytes(data))
    return off, bit


def block_of(
    root: Path, array: str, chunk: Path, shard: tuple[int, int] = (1, 1)
) -> tuple[int, int]:
    """First block covered by a chunk file (``c/<r>/<c>/...``), scaled by the shard shape."""
    parts = chunk.relative_to(root / array / "c").parts
    return int(parts[0]) * shard[0], int(parts[1]) * shard[1]
