"""Helpers for store tests: comparing two stores byte for byte, damaging chunks on purpose."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import zarr.storage

import tiler.journal_reads as journal_reads
from tiler.journal_reads import JOURNAL
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


class JournalReads:
    """Journal chunk reads from local stores (zarr's ``LocalStore.get`` patched), counted
    (``reads``: found, ``absent``: a look for one not there); ``damage``: keys whose file is
    damaged on disk (a byte flipped) just before their first read that finds one; ``fail``:
    keys whose first ``n`` reads raise a transport error instead."""

    def __init__(self, monkeypatch, root: Path, damage=(), fail: dict[str, int] | None = None):
        monkeypatch.setattr(journal_reads, "JOURNAL_RETRY_WAIT_S", 0.0)
        self.reads: Counter = Counter()
        self.absent: Counter = Counter()
        self.failed: Counter = Counter()
        todo, fail = set(damage), fail or {}
        real = zarr.storage.LocalStore.get
        outer = self

        async def get(store, key, *args, **kwargs):
            if not key.startswith(f"{JOURNAL}/c."):
                return await real(store, key, *args, **kwargs)
            if key in todo and (root / key).is_file():
                todo.discard(key)
                raw = bytearray((root / key).read_bytes())
                raw[len(raw) // 2] ^= 0xFF
                (root / key).write_bytes(bytes(raw))
            if outer.failed[key] < fail.get(key, 0):
                outer.failed[key] += 1
                raise ConnectionResetError(f"simulated: connection reset reading {key}")
            out = await real(store, key, *args, **kwargs)
            (outer.absent if out is None else outer.reads)[key] += 1
            return out

        monkeypatch.setattr(zarr.storage.LocalStore, "get", get)
