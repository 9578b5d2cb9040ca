"""Resuming reads each journal entry once (audit 45): the done blocks, the check of their
source samples and the shards of the small levels all come from one read (three GETs a block on
S3 before), a shard region at a time; the resumed store stays the uninterrupted run's."""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np
import pytest
import rasterio
import zarr.storage
from demtools import fractal, write_dem
from storetools import diff_stores

import tiler.tile as tile_mod
from tiler.errors import JobMismatchError
from tiler.tile import TileOptions, tile

# 150x40 samples in blocks of 9 (sharing an edge: a step of 8): 19x5 blocks, in shards of
# 16x16 blocks (two shards)
OPTS = TileOptions(block_size=9, workers=2, executor="threads")
BLOCKS = 19 * 5
#: blocks done before the Ctrl-C: rows 0..15 and 2 blocks of row 16 (shard (0, 0) all done,
#: (1, 0) partly done)
DONE_BEFORE = 16 * 5 + 2


def _interrupted(monkeypatch, src, dst, n=DONE_BEFORE, opts=OPTS):
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
        tile(src, dst, opts)
    monkeypatch.setattr(tile_mod, "process_block", real)


def _count_journal_reads(monkeypatch) -> Counter:
    """Count the reads of each written journal chunk (``journal/c.R.C.0``) from local stores
    (a look for one not written yet, which finds nothing, is not counted)."""
    reads: Counter = Counter()
    real = zarr.storage.LocalStore.get

    async def get(self, key, *args, **kwargs):
        out = await real(self, key, *args, **kwargs)
        if key.startswith("journal/c.") and out is not None:
            reads[key] += 1
        return out

    monkeypatch.setattr(zarr.storage.LocalStore, "get", get)
    return reads


@pytest.fixture
def dem(tmp_path):
    return write_dem(tmp_path / "dem.tif", fractal((150, 40), 7))


def test_a_resume_reads_each_journal_entry_once(tmp_path, monkeypatch, dem):
    """Every journal entry written before the Ctrl-C is read once by the resume (three times
    before: ``done_blocks``, ``changed_done_blocks`` and the shard's flush), and so is every
    entry the resume writes; the store is the uninterrupted run's, byte for byte."""
    ref = tile(dem, tmp_path / "ref.zarr", OPTS).location.path
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, dem, dst)
    before = {p.name for p in (dst / "journal").glob("c.*")}
    assert 0 < len(before) < BLOCKS
    reads = _count_journal_reads(monkeypatch)
    store = tile(dem, dst, OPTS)
    assert store.tile_summary.resumed
    assert store.tile_summary.blocks_skipped == len(before)
    old = Counter({k: v for k, v in reads.items() if k.split("/")[1] in before})
    assert set(old) == {f"journal/{name}" for name in before}
    assert max(old.values()) == 1, old.most_common(3)
    assert max(reads.values()) == 1, reads.most_common(3)  # (the new ones too)
    assert len(reads) == BLOCKS
    assert diff_stores(dst, ref) == []


@pytest.mark.parametrize("where", [(3, 4), (16, 0)], ids=["all-done-shard", "part-done-shard"])
def test_a_damaged_journal_entry_is_computed_again(tmp_path, monkeypatch, dem, where):
    """A journal entry whose crc32c fails (in a shard otherwise all done, or one partly done)
    is not done: its block is computed again, the others are not, and the store is the
    uninterrupted run's, byte for byte."""
    ref = tile(dem, tmp_path / "ref.zarr", OPTS).location.path
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, dem, dst)
    entry = dst / "journal" / f"c.{where[0]}.{where[1]}.0"
    assert entry.exists()
    n_before = len(list((dst / "journal").glob("c.*")))
    raw = bytearray(entry.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    entry.write_bytes(bytes(raw))
    store = tile(dem, dst, OPTS)
    assert store.tile_summary.resumed
    assert store.tile_summary.blocks_skipped == n_before - 1
    assert diff_stores(dst, ref) == []


def test_a_source_changed_under_a_later_shard_is_refused_then_resumes(tmp_path, monkeypatch):
    """A source edited in place under a done block of the second shard row (the first shards
    all done, so written as the journal is read) and outside the fingerprint's windows is
    refused naming that block; with the original samples back the resume gives the
    uninterrupted run's store."""
    # 600x40 samples (the fingerprint's windows leave rows 256..299 out) in blocks of 17 (a step
    # of 16): 38x3 blocks, in shards of 16x3
    dem = write_dem(tmp_path / "big.tif", fractal((600, 40), 11))  # uncompressed
    opts = TileOptions(block_size=17, workers=2, executor="threads")
    ref = tile(dem, tmp_path / "ref.zarr", opts).location.path
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, dem, dst, n=16 * 3 + 2, opts=opts)
    assert (dst / "journal" / "c.16.0.0").exists()
    size = dem.stat().st_size
    window = rasterio.windows.Window(3, 16 * 16 + 2, 4, 3)  # inside block (16, 0) only
    with rasterio.open(dem, "r+") as ds:
        data = ds.read(1, window=window)
        ds.write(data + np.int16(50), 1, window=window)
    assert dem.stat().st_size == size
    with pytest.raises(JobMismatchError, match=r"1 block\(s\) already done differ \(\(16, 0\)\)"):
        tile(dem, dst, opts)
    with rasterio.open(dem, "r+") as ds:
        ds.write(data, 1, window=window)
    store = tile(dem, dst, opts)
    assert store.tile_summary.resumed
    assert diff_stores(dst, ref) == []


def _flush_guards(monkeypatch, tmp_path, guard_resumed: bool) -> list[tuple[tuple, bool]]:
    """Interrupt, then resume with every shard write recorded with whether a Ctrl-C would be
    deferred over it (``guard_resumed`` False: the resume's early writes run unguarded, as
    first written)."""
    import tiler.assemble as asm_mod
    import tiler.interrupt as intr

    dem = write_dem(tmp_path / "d.tif", fractal((150, 40), 3))
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, dem, dst)
    seen = []
    real_write = asm_mod.write_small_levels

    def spy(loc, meta, entries, region):
        seen.append((region, bool(intr._ACTIVE)))
        return real_write(loc, meta, entries, region)

    monkeypatch.setattr(asm_mod, "write_small_levels", spy)
    if not guard_resumed:
        monkeypatch.setattr(asm_mod, "DeferredInterrupt", _NoDefer)
    tile(dem, dst, OPTS)
    return seen


class _NoDefer:
    """A stand-in for ``DeferredInterrupt`` that defers nothing (the positive control)."""

    def __init__(self, **kw) -> None:
        self.interrupted = False

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None


def test_a_resumes_shard_writes_defer_a_ctrl_c(monkeypatch, tmp_path):
    """The all-done shard a resume writes while it reads the journal is written with a Ctrl-C
    deferred, as every other shard write: raised inside zarr's synchronous calls it left writes
    pending on zarr's loop while the lease was released (review of ccdd73f)."""
    seen = _flush_guards(monkeypatch, tmp_path, guard_resumed=True)
    assert [r for r, _ in seen] == [(0, 16, 0, 5), (16, 19, 0, 5)]  # the early one first
    assert all(deferred for _, deferred in seen), seen


def test_control_without_the_guard_the_early_shard_write_is_unguarded(monkeypatch, tmp_path):
    seen = _flush_guards(monkeypatch, tmp_path, guard_resumed=False)
    assert not all(deferred for _, deferred in seen), seen
