"""A block's journal entry (its commit) is written directly on a local store (audit 46), as its
level, error and mask chunks are: zarr's key (``journal/c.<r>.<c>.0``, the journal's ``.``
separator) and zarr's bytes, after the block's data chunks; a run interrupted with direct
entries resumes to the uninterrupted store, byte for byte. ``TERRASTREAM_DIRECT_WRITES=0``
writes the entries through zarr (the reference)."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest
import zarr
from demtools import fractal, write_dem
from storetools import diff_stores

import tiler.tile as tile_mod
from tiler import chunkread, chunkwrite
from tiler import run as run_mod
from tiler.layout import level_size
from tiler.resume import (
    JOURNAL,
    JournalEntry,
    create_journal,
    done_blocks,
    entry_nbytes,
    pack,
    small_levels,
    unpack,
)
from tiler.tile import TileOptions, tile

# 200x200 samples in blocks of 65 (a step of 64): 4x4 blocks, k = 6 (level 6 written per block,
# levels 0..5 in the journal)
SIZE = (200, 200)
OPTS = TileOptions(block_size=65, workers=1, executor="threads")
BLOCKS = 4 * 4
DONE_BEFORE = 6
BLOCKS_WRITTEN = [(0, 0), (0, 3), (1, 2), (2, 3), (2, 0)]


def _files(root: Path, array: str) -> dict[str, bytes]:
    """Every chunk file of ``array`` by its path relative to the store (``/``-joined)."""
    base = root / array
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(base.rglob("*"))
        if p.is_file() and p.name != "zarr.json"
    }


def _entry(rng: np.random.Generator, k: int, storage_dtype: str, i: int) -> JournalEntry:
    hi = np.iinfo(np.dtype(storage_dtype)).max
    levels = [
        rng.integers(0, hi, level_size(lv), dtype=np.dtype(storage_dtype), endpoint=True)
        for lv in range(small_levels(k))
    ]
    return JournalEntry(levels, bool(i % 2), bool(i % 3 == 0), -12.5 + i, 830.25 * (i + 1),
                        int(rng.integers(0, 2**63)), int(rng.integers(0, 2**63)))  # fmt: skip


def _journals(tmp_path: Path, k: int, storage_dtype: str) -> tuple[Path, Path]:
    out = []
    for name in ("zarr", "direct"):
        root = tmp_path / f"{name}.zarr"
        create_journal(zarr.open_group(root, mode="w"), 3, 4, k, storage_dtype)
        out.append(root)
    return out[0], out[1]


def _journal_spec(root: Path) -> chunkwrite.ChunkSpec:
    spec = chunkwrite.chunk_spec(JOURNAL, zarr.open_array(root, path=JOURNAL).metadata.to_dict())
    assert spec is not None
    return spec


@pytest.mark.parametrize("k", [3, 10])
@pytest.mark.parametrize("storage_dtype", ["uint16", "uint32"], ids=["int16", "float32"])
def test_journal_entries_are_zarrs_key_and_bytes(tmp_path, storage_dtype, k):
    """Entries of several blocks (int16 and float32 DEMs' storage dtypes, 4 and 6 journaled
    levels) written directly are the files zarr writes: the same names, the same bytes; and
    they read back through zarr as the entries packed."""
    via_zarr, direct = _journals(tmp_path, k, storage_dtype)
    arr = run_mod.open_for_write(via_zarr, JOURNAL)
    spec = _journal_spec(direct)
    assert spec.separator == "." and spec.shape == (entry_nbytes(k, storage_dtype),)
    rng = np.random.default_rng(46)
    entries = {}
    for i, b in enumerate(BLOCKS_WRITTEN):
        entries[b] = _entry(rng, k, storage_dtype, i)
        raw = pack(entries[b], storage_dtype)
        arr[b] = raw
        n = chunkwrite.write_local(str(direct), spec, b, raw)
        assert spec.key(b) == f"{JOURNAL}/c.{b[0]}.{b[1]}.0"
        assert (direct / spec.key(b)).stat().st_size == n
    a, z = _files(direct, JOURNAL), _files(via_zarr, JOURNAL)
    assert sorted(a) == sorted(z) == sorted(f"{JOURNAL}/c.{r}.{c}.0" for r, c in BLOCKS_WRITTEN)
    assert [key for key in a if a[key] != z[key]] == []
    back = zarr.open_array(direct, path=JOURNAL)
    want = np.zeros((3, 4), bool)
    want[tuple(zip(*BLOCKS_WRITTEN, strict=True))] = True
    assert np.array_equal(done_blocks(back), want)
    for b, e in entries.items():
        got = unpack(back[b], k, storage_dtype)
        assert [lv.tolist() for lv in got.levels] == [lv.tolist() for lv in e.levels]
        assert dataclasses.replace(got, levels=[]) == dataclasses.replace(e, levels=[])


def test_a_wrong_separator_is_not_read_by_zarr(tmp_path):
    """Positive control for the key test above: the same bytes under ``/``-separated keys
    (``journal/c/1/2/0``) are files the journal's zarr reads do not see, so the block reads as
    not done and the file comparison tells the stores apart."""
    via_zarr, direct = _journals(tmp_path, 7, "uint16")
    arr = run_mod.open_for_write(via_zarr, JOURNAL)
    wrong = dataclasses.replace(_journal_spec(direct), separator="/")
    raw = pack(_entry(np.random.default_rng(1), 7, "uint16", 0), "uint16")
    arr[1, 2] = raw
    chunkwrite.write_local(str(direct), wrong, (1, 2), raw)
    assert (direct / JOURNAL / "c" / "1" / "2" / "0").is_file()
    assert not done_blocks(zarr.open_array(direct, path=JOURNAL)).any()
    assert done_blocks(zarr.open_array(via_zarr, path=JOURNAL))[1, 2]
    a, z = _files(direct, JOURNAL), _files(via_zarr, JOURNAL)
    assert sorted(a) != sorted(z)
    assert list(a.values()) == list(z.values())  # the bytes alone would not have told


def test_the_readers_still_refuse_dot_keys(tmp_path):
    """Only the writer opts in to ``.`` keys: chunkread's specs (``/`` keys, LevelSpec.key)
    still leave the journal to zarr, and accept the same metadata with ``/`` keys (control:
    the separator is what they refuse)."""
    root, _ = _journals(tmp_path, 7, "uint16")
    meta = zarr.open_array(root, path=JOURNAL).metadata.to_dict()
    assert chunkread.block_spec(JOURNAL, meta) is None
    assert chunkread.regular_array(meta) is None
    assert chunkread.regular_array(meta, ("/", ".")) is not None
    slash = dict(meta, chunk_key_encoding={"name": "default", "configuration": {"separator": "/"}})
    assert chunkread.block_spec(JOURNAL, slash) is not None
    assert chunkwrite.chunk_spec(JOURNAL, slash).key((1, 2)) == f"{JOURNAL}/c/1/2/0"
    assert chunkwrite.chunk_spec(JOURNAL, meta).key((1, 2)) == f"{JOURNAL}/c.1.2.0"
    odd = dict(meta, chunk_key_encoding={"name": "default", "configuration": {"separator": "-"}})
    assert chunkwrite.chunk_spec(JOURNAL, odd) is None


def _record_writes(monkeypatch) -> list[tuple[str, tuple[int, int]]]:
    """``(array, block)`` of every direct chunk write, in order."""
    writes: list[tuple[str, tuple[int, int]]] = []
    for name in ("write_local", "write_local_bytes"):
        real = getattr(chunkwrite, name)

        def f(root, spec, block, *a, _real=real):
            writes.append((spec.name, tuple(block)))
            return _real(root, spec, block, *a)

        monkeypatch.setattr(chunkwrite, name, f)
    return writes


def _interrupted(monkeypatch, src: Path, dst: Path, n: int = DONE_BEFORE) -> None:
    """Tile ``src`` into ``dst`` until ``n`` blocks are done, then a Ctrl-C: unfinished."""
    real = tile_mod.process_block
    count = {"n": 0}
    lock = threading.Lock()

    def flaky(window, params):
        with lock:
            count["n"] += 1
            if count["n"] > n:
                raise KeyboardInterrupt("simulated Ctrl-C")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", flaky)
    with pytest.raises(KeyboardInterrupt):
        tile(src, dst, OPTS)
    monkeypatch.setattr(tile_mod, "process_block", real)


@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_interrupted_stores_hold_zarrs_journal_and_resume_exactly(monkeypatch, tmp_path, dtype):
    """Interrupted after the same blocks, a run writing its entries directly and one writing
    through zarr (``TERRASTREAM_DIRECT_WRITES=0``) leave the same journal files, byte for
    byte, and the same data chunks; each entry was written after its block's data chunks.
    Both resume (skipping the done blocks) to stores byte-identical to each other and to an
    uninterrupted run."""
    data = fractal(SIZE, 46, dtype)
    data[30:60, 5:170] = -9999  # (nodata: sparse blocks and masks)
    src = write_dem(tmp_path / "dem.tif", data, nodata=-9999)
    direct, via_zarr = tmp_path / "direct.zarr", tmp_path / "zarr.zarr"
    writes = _record_writes(monkeypatch)
    _interrupted(monkeypatch, src, direct)
    journal_writes = [b for name, b in writes if name == JOURNAL]
    assert len(journal_writes) == DONE_BEFORE
    for b in journal_writes:  # the commit comes after the block's data chunks
        mine = [name for name, blk in writes if blk == b]
        assert mine[-1] == JOURNAL and mine.count(JOURNAL) == 1 and "levels/6" in mine, mine
    n_direct = len(writes)
    monkeypatch.setenv(run_mod.DIRECT_WRITES_ENV, "0")
    _interrupted(monkeypatch, src, via_zarr)
    assert len(writes) == n_direct  # the switch sends every write, the entries too, to zarr
    for array in (JOURNAL, "levels", "errors", "mask"):
        a, z = _files(direct, array), _files(via_zarr, array)
        assert a and sorted(a) == sorted(z), array
        assert [key for key in a if a[key] != z[key]] == [], array
    assert len(_files(direct, JOURNAL)) == DONE_BEFORE

    s = tile(src, via_zarr, OPTS)
    monkeypatch.delenv(run_mod.DIRECT_WRITES_ENV)
    assert s.tile_summary.blocks_skipped == DONE_BEFORE
    s = tile(src, direct, OPTS)
    assert s.tile_summary.resumed and s.tile_summary.blocks_skipped == DONE_BEFORE
    assert s.tile_summary.blocks_computed == BLOCKS - DONE_BEFORE
    assert sum(name == JOURNAL for name, _ in writes) == BLOCKS
    ref = tile(src, tmp_path / "ref.zarr", OPTS).location.path
    assert not (direct / JOURNAL).exists()
    assert diff_stores(direct, via_zarr) == []
    assert diff_stores(direct, ref) == []


def test_a_wrong_journal_key_loses_the_done_blocks(monkeypatch, tmp_path):
    """Positive control for the resume test: entries written under keys zarr does not read
    (``/`` instead of ``.``) leave no block done, so the resume (by the right writer)
    computes every block again (the test above counts the skipped blocks)."""
    real = chunkwrite.chunk_spec

    def wrong(name, metadata):
        spec = real(name, metadata)
        if spec is not None and name == JOURNAL:
            spec = dataclasses.replace(spec, separator="/")
        return spec

    monkeypatch.setattr(chunkwrite, "chunk_spec", wrong)
    src = write_dem(tmp_path / "dem.tif", fractal(SIZE, 46))
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, src, dst)
    assert len(_files(dst, JOURNAL)) == DONE_BEFORE
    assert (dst / JOURNAL / "c").is_dir() and not list((dst / JOURNAL).glob("c.*"))
    monkeypatch.setattr(chunkwrite, "chunk_spec", real)
    s = tile(src, dst, OPTS)
    assert s.tile_summary.blocks_skipped == 0 and s.tile_summary.blocks_computed == BLOCKS
