"""A repair reads each journal entry once (audit 46), and a journal read the store's transport
fails is tried again, then stops a resume, rather than compute its blocks again.

Before, finishing an interrupted repair read its journal twice (``done_blocks``, then ``_patch``
block by block), and ``_patch`` read the entries one zarr call a block (on S3, one GET after
another). A transport error reading journal entries (an ``OSError``: a dropped connection, a
5xx past the client's retries) sent the reader to read the region's entries one by one, and an
entry whose read failed again was counted as not done, so its block was silently computed again:
correct, but hours on a big job for a failing network. The read is now tried once more (the
whole region); failing again, the run stops with :class:`StoreUnavailableError` naming the
store (exit 1), to be rerun. A damaged entry (its crc32c failing) is still computed again.
"""

from __future__ import annotations

import asyncio
import shutil
import threading
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zarr
import zarr.storage
from demtools import fractal, write_dem
from storetools import diff_stores

import tiler.journal_reads as journal_mod
import tiler.tile as tile_mod
from tiler.errors import StoreUnavailableError
from tiler.meta import read_meta
from tiler.resume import JOURNAL, create_journal, done_blocks, read_journal_region
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

# 150x16 samples in blocks of 9 (a step of 8): 19x2 blocks, in shards of 16x2 (two shards)
OPTS = TileOptions(block_size=9, workers=2, executor="threads")
REPAIR = TileOptions(block_size=9, workers=2, executor="threads", repair=True)
SHARD = (16, 2)
#: the blocks damaged (their level-0 chunk inside the shard): three in shard (0, 0), one in (1, 0)
DAMAGED = [(2, 1), (3, 0), (5, 0), (17, 1)]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The DEM, its store (the reference) and a copy with :data:`DAMAGED` damaged."""
    d = tmp_path_factory.mktemp("audit46")
    src = write_dem(d / "dem.tif", fractal((150, 16), 7))
    ref = tile(src, d / "ref.zarr", OPTS).location.path
    damaged = d / "damaged.zarr"
    shutil.copytree(ref, damaged)
    for br, bc in DAMAGED:
        shard = damaged / "levels/0/c" / str(br // SHARD[0]) / str(bc // SHARD[1]) / "0"
        _flip_inner(shard, SHARD[0] * SHARD[1], (br % SHARD[0]) * SHARD[1] + bc % SHARD[1])
    assert verify_store(damaged).bad_blocks == set(DAMAGED)
    return src, ref, damaged


def _flip_inner(shard: Path, n_inner: int, inner: int) -> None:
    """Flip a byte in the middle of inner chunk ``inner`` of a shard (its crc32c then fails)."""
    data = bytearray(shard.read_bytes())
    idx = np.frombuffer(bytes(data[-(n_inner * 16 + 4) : -4]), "<u8").reshape(-1, 2)
    off, nbytes = (int(v) for v in idx[inner])
    data[off + nbytes // 2] ^= 0xFF
    shard.write_bytes(bytes(data))


def _damaged_copy(made, dst: Path) -> Path:
    """A copy of the store with the level-0 chunks of :data:`DAMAGED` damaged."""
    return Path(shutil.copytree(made[2], dst))


class _JournalReads:
    """Counts the reads of each written journal chunk from local stores (a look for one not
    written, which finds nothing, is not counted) and the most under way at once; ``fail``:
    the keys whose first ``n`` reads raise a transport error instead (then they answer)."""

    def __init__(self, monkeypatch, fail: dict[str, int] | None = None) -> None:
        fail = fail or {}
        monkeypatch.setattr(journal_mod, "JOURNAL_RETRY_WAIT_S", 0.0, raising=False)
        self.reads: Counter = Counter()
        self.failed: Counter = Counter()
        self.inflight = self.most = 0
        real = zarr.storage.LocalStore.get
        outer = self

        async def get(store, key, *args, **kwargs):
            if not key.startswith(f"{JOURNAL}/c."):
                return await real(store, key, *args, **kwargs)
            if outer.failed[key] < fail.get(key, 0):
                outer.failed[key] += 1
                raise ConnectionResetError(f"simulated: connection reset reading {key}")
            outer.inflight += 1
            outer.most = max(outer.most, outer.inflight)
            try:
                await asyncio.sleep(0.005)  # (reads fetched together overlap here)
                out = await real(store, key, *args, **kwargs)
            finally:
                outer.inflight -= 1
            if out is not None:
                outer.reads[key] += 1
            return out

        monkeypatch.setattr(zarr.storage.LocalStore, "get", get)


def _interrupted_repair(monkeypatch, s: Path, src, n: int) -> set[str]:
    """Repair ``s`` until ``n`` blocks are recomputed, then a Ctrl-C (the store left in state
    ``repair``); returns the journal chunks written."""
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
        tile(src, s, TileOptions(block_size=9, workers=1, executor="threads", repair=True))
    monkeypatch.setattr(tile_mod, "process_block", real)
    assert _state(s) == "repair"
    return {f"{JOURNAL}/{p.name}" for p in (s / JOURNAL).glob("c.*")}


def _state(s: Path) -> str | None:
    """The store's ``state`` (None: finished)."""
    return read_meta(zarr.open_group(s, mode="r")).extra.get("state")


# -- task 1: each journal entry read once, a shard's together -----------------------------------


def test_a_repair_reads_each_entry_once_a_shards_entries_together(made, tmp_path, monkeypatch):
    """The damaged blocks' journal entries are read once each, those of one shard fetched
    together (the control, the code before: one zarr call a block, never two reads under way);
    the repaired store is the reference, byte for byte."""
    src, ref, _ = made
    s = _damaged_copy(made, tmp_path / "s.zarr")
    seen = _JournalReads(monkeypatch)
    store = tile(src, s, REPAIR)
    assert store.tile_summary.blocks_computed == len(DAMAGED)
    assert dict(seen.reads) == {f"{JOURNAL}/c.{r}.{c}.0": 1 for r, c in DAMAGED}
    assert seen.most == 3, seen.most  # the three of shard (0, 0) at once
    assert _state(s) is None and diff_stores(s, ref) == []


def test_a_resumed_repair_reads_each_entry_once(made, tmp_path, monkeypatch):
    """Finishing an interrupted repair reads each entry its journal holds once (twice before:
    ``done_blocks``, then ``_patch``), and each entry it writes once; the blocks recomputed
    before are not computed again, and the store is the reference, byte for byte."""
    src, ref, _ = made
    s = _damaged_copy(made, tmp_path / "s.zarr")
    before = _interrupted_repair(monkeypatch, s, src, n=2)
    assert 0 < len(before) < len(DAMAGED)
    seen = _JournalReads(monkeypatch)
    store = tile(src, s, REPAIR)
    assert store.tile_summary.blocks_skipped == len(before)
    assert store.tile_summary.blocks_computed == len(DAMAGED) - len(before)
    assert set(seen.reads) == {f"{JOURNAL}/c.{r}.{c}.0" for r, c in DAMAGED}
    assert max(seen.reads.values()) == 1, seen.reads.most_common(3)
    assert _state(s) is None and diff_stores(s, ref) == []


def test_a_damaged_entry_of_an_interrupted_repair_is_computed_again(made, tmp_path, monkeypatch):
    """A journal entry of an interrupted repair whose crc32c fails is not taken: its block
    (still damaged) is computed again, as before; the store is the reference, byte for byte."""
    src, ref, _ = made
    s = _damaged_copy(made, tmp_path / "s.zarr")
    before = sorted(_interrupted_repair(monkeypatch, s, src, n=2))
    entry = s / before[0]
    raw = bytearray(entry.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    entry.write_bytes(bytes(raw))
    store = tile(src, s, REPAIR)
    assert store.tile_summary.blocks_skipped == len(before) - 1
    assert store.tile_summary.blocks_computed == len(DAMAGED) - len(before) + 1
    assert _state(s) is None and diff_stores(s, ref) == []


# -- task 2: a transport error reading the journal stops the resume -----------------------------


def test_a_transport_error_reading_an_interrupted_repairs_journal_stops_it(
    made, tmp_path, monkeypatch
):
    """A connection dropped on both reads of a journal entry of an interrupted repair stops the
    repair naming the store and what to do (the control, the code before: that entry was not
    done, its block computed again); rerun, it finishes from the entries kept, byte for byte
    the reference."""
    src, ref, _ = made
    s = _damaged_copy(made, tmp_path / "s.zarr")
    before = sorted(_interrupted_repair(monkeypatch, s, src, n=2))
    seen = _JournalReads(monkeypatch, fail={before[0]: 2})
    with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
        tile(src, s, REPAIR)
    assert str(s) in str(info.value) and "ConnectionResetError" in str(info.value)
    assert seen.failed[before[0]] == 2 and _state(s) == "repair"
    monkeypatch.undo()
    store = tile(src, s, REPAIR)
    assert store.tile_summary.blocks_skipped == len(before)
    assert _state(s) is None and diff_stores(s, ref) == []


def _interrupted_tiling(monkeypatch, src, dst: Path, n: int) -> set[str]:
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
    return {f"{JOURNAL}/{p.name}" for p in (dst / JOURNAL).glob("c.*")}


@pytest.mark.parametrize("shard", ["all-done", "part-done"])
def test_a_transport_error_reading_the_journal_stops_a_resume(made, tmp_path, monkeypatch, shard):
    """A connection dropped on both reads of a done block's journal entry stops the resume
    before any block is computed, naming the store (the control, the code before: that block
    was computed again, ``blocks_skipped`` one short); rerun, it resumes every done block and
    gives the reference, byte for byte."""
    src, ref, _ = made
    dst = tmp_path / "s.zarr"
    before = _interrupted_tiling(monkeypatch, src, dst, n=16 * 2 + 1)
    key = f"{JOURNAL}/c.3.1.0" if shard == "all-done" else sorted(before)[-1]
    assert key in before
    seen = _JournalReads(monkeypatch, fail={key: 2})
    with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
        tile(src, dst, OPTS)
    assert str(dst) in str(info.value) and "connection reset" in str(info.value)
    assert seen.failed[key] == 2
    assert {f"{JOURNAL}/{p.name}" for p in (dst / JOURNAL).glob("c.*")} == before
    monkeypatch.undo()
    store = tile(src, dst, OPTS)
    assert store.tile_summary.resumed and store.tile_summary.blocks_skipped == len(before)
    assert diff_stores(dst, ref) == []


def test_a_transient_transport_error_is_read_again(made, tmp_path, monkeypatch, caplog):
    """The normal case: a connection dropped once reading a done block's journal entry is
    read again (with a warning): the resume goes on, no done block is computed again, and the
    store is the reference, byte for byte."""
    src, ref, _ = made
    dst = tmp_path / "s.zarr"
    before = _interrupted_tiling(monkeypatch, src, dst, n=16 * 2 + 1)
    seen = _JournalReads(monkeypatch, fail={f"{JOURNAL}/c.3.1.0": 1})
    with caplog.at_level("WARNING", logger="tiler.tile"):
        store = tile(src, dst, OPTS)
    assert seen.failed[f"{JOURNAL}/c.3.1.0"] == 1 and "trying again" in caplog.text
    assert store.tile_summary.resumed and store.tile_summary.blocks_skipped == len(before)
    assert diff_stores(dst, ref) == []


def test_the_cli_exits_1_naming_the_store(made, tmp_path, monkeypatch):
    """``terrastream tile`` resuming over a journal its store fails to read exits 1 with one
    line naming the store and saying to rerun."""
    from typer.testing import CliRunner

    from cli.main import app

    src, _, _ = made
    dst = tmp_path / "s.zarr"
    before = _interrupted_tiling(monkeypatch, src, dst, n=10)
    _JournalReads(monkeypatch, fail={sorted(before)[0]: 2})
    args = ["tile", str(src), str(dst), "--block-size", "9", "--workers", "2"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1, res.output
    assert "rerun the same command" in res.output and str(dst) in res.output, res.output


# -- the journal readers themselves --------------------------------------------------------------


def _journal(tmp_path: Path) -> zarr.Array:
    """A 3x4 journal (k = 3) with every entry but (2, 3) written."""
    g = zarr.open_group(tmp_path / "j.zarr", mode="w")
    create_journal(g, 3, 4, 3, "int16")
    arr = g[JOURNAL]
    for br in range(3):
        for bc in range(4):
            if (br, bc) != (2, 3):
                arr[br, bc] = np.full(arr.shape[2], 1, np.uint8)
    return arr


def test_the_journal_readers_tell_damage_from_a_transport_error(tmp_path, monkeypatch):
    """A damaged entry reads as not done (zero); an entry whose read the transport fails raises
    :class:`StoreUnavailableError` naming the store (the control, the code before: read as not
    done, as if damaged)."""
    arr = _journal(tmp_path)
    expected = np.ones((3, 4), bool)
    expected[2, 3] = False
    assert np.array_equal(done_blocks(arr), expected)  # (the intact journal)
    entry = tmp_path / "j.zarr" / JOURNAL / "c.1.2.0"
    raw = bytearray(entry.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    entry.write_bytes(bytes(raw))
    expected[1, 2] = False
    assert np.array_equal(done_blocks(arr), expected)
    assert not read_journal_region(arr, 0, 3, 0, 4)[1, 2].any()
    for read in (lambda: done_blocks(arr), lambda: read_journal_region(arr, 0, 3, 0, 4)):
        monkeypatch.undo()
        _JournalReads(monkeypatch, fail={f"{JOURNAL}/c.0.1.0": 2})
        with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
            read()
        assert "j.zarr" in str(info.value) and info.value.array == JOURNAL
    monkeypatch.undo()  # the normal case: failing once, it is read again
    seen = _JournalReads(monkeypatch, fail={f"{JOURNAL}/c.0.1.0": 1})
    assert np.array_equal(done_blocks(arr), expected)
    assert seen.failed[f"{JOURNAL}/c.0.1.0"] == 1
