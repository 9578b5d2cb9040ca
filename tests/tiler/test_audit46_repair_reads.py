"""What a repair and a shard flush read (audit 46, after the journal was read once).

1. A repair rebuilds a shard of the small levels around the blocks it recomputed: the blocks
   that verified clean are read back from the old shard. They were read one zarr call a block
   and a level (255 x 6 calls for one block of a 16x16 shard at k >= 5, two GETs each on S3:
   the shard index, then the chunk); each level's shard is now fetched once, and only the clean
   blocks' chunks decoded. The written shards are those of an uninterrupted tiling, byte for
   byte.
2. The tiling's shard flush read its blocks' journal entries with no care for damage or the
   transport: zarr's raw error. A damaged entry now stops the run with
   :class:`StoreCorruptError` naming the block and to rerun (the resume computes it again); a
   transport failure is tried again, then :class:`StoreUnavailableError` naming the store.
3. Finishing an interrupted repair asked the store for every journal key (most absent: a 404
   each on S3); it now lists the journal's keys and reads only those there.
"""

from __future__ import annotations

import shutil
import threading
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zarr
import zarr.storage
from demtools import fractal, write_dem
from storetools import JournalReads, diff_stores

import tiler.assemble as asm_mod
import tiler.journal_reads as journal_mod
import tiler.repair as repair_mod
import tiler.tile as tile_mod
from tiler.errors import StoreCorruptError, StoreUnavailableError
from tiler.location import Location
from tiler.meta import read_meta
from tiler.resume import JOURNAL, create_journal
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

# -- 1: the clean blocks of a rebuilt shard, read a level at a time ------------------------------

# 137x137 samples in blocks of 9 (a step of 8): 17x17 blocks, k = 3 (levels 0..3 all sharded),
# shards of 16x16 blocks: (0, 0) 16x16, (0, 1) 16x1, (1, 0) 1x16, (1, 1) 1x1
BIG = TileOptions(block_size=9, workers=2, executor="threads")
BIG_REPAIR = TileOptions(block_size=9, workers=2, executor="threads", repair=True)
BIG_SHARD = 16
#: damaged blocks and the level of each whose chunk is damaged: two in the 16x16 shard (two
#: levels), one in the 16x1 shard, the one block of the 1x1 shard (no clean block to read)
BIG_DAMAGED = {(5, 7): 0, (9, 2): 2, (3, 16): 1, (16, 16): 3}


def _flip_inner(shard: Path, n_inner: int, inner: int) -> None:
    """Flip a byte in the middle of inner chunk ``inner`` of a shard (its crc32c then fails)."""
    data = bytearray(shard.read_bytes())
    idx = np.frombuffer(bytes(data[-(n_inner * 16 + 4) : -4]), "<u8").reshape(-1, 2)
    off, nbytes = (int(v) for v in idx[inner])
    data[off + nbytes // 2] ^= 0xFF
    shard.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """The 17x17-block DEM, its store (the reference) and a copy with :data:`BIG_DAMAGED`
    damaged."""
    d = tmp_path_factory.mktemp("audit46_reads")
    src = write_dem(d / "dem.tif", fractal((137, 137), 11))
    ref = tile(src, d / "ref.zarr", BIG).location.path
    damaged = Path(shutil.copytree(ref, d / "damaged.zarr"))
    for (br, bc), level in BIG_DAMAGED.items():
        # (an edge shard's index has room for 16x16 inner chunks too)
        shard = damaged / f"levels/{level}/c/{br // BIG_SHARD}/{bc // BIG_SHARD}/0"
        _flip_inner(shard, BIG_SHARD * BIG_SHARD, (br % BIG_SHARD) * BIG_SHARD + bc % BIG_SHARD)
    return src, ref, damaged


class _LevelReads:
    """Counts the reads of the small levels' shards (those finding bytes) made while
    ``write_small_levels`` runs, by key."""

    def __init__(self, monkeypatch) -> None:
        self.reads: Counter = Counter()
        self.inside = False
        real_get = zarr.storage.LocalStore.get
        real_write = repair_mod.write_small_levels
        outer = self

        async def get(store, key, *args, **kwargs):
            out = await real_get(store, key, *args, **kwargs)
            if outer.inside and key.startswith("levels/") and "/c/" in key and out is not None:
                outer.reads[key] += 1
            return out

        def write_small_levels(*args, **kwargs):
            outer.inside = True
            try:
                return real_write(*args, **kwargs)
            finally:
                outer.inside = False

        monkeypatch.setattr(zarr.storage.LocalStore, "get", get)
        monkeypatch.setattr(repair_mod, "write_small_levels", write_small_levels)


def test_a_repair_reads_each_rebuilt_shard_once_a_level(big, tmp_path, monkeypatch):
    """Rebuilding a shard reads each small level's old shard once (the control, the code
    before: two reads a clean block and a level, 2 x 254 x 4 of the 16x16 shard); the shard of
    one block, all of it rebuilt, is not read; the repaired store is the reference, byte for
    byte (the damaged chunks, those of the repaired blocks, are never decoded: no error)."""
    src, ref, damaged = big
    s = Path(shutil.copytree(damaged, tmp_path / "s.zarr"))
    seen = _LevelReads(monkeypatch)
    store = tile(src, s, BIG_REPAIR)
    assert store.tile_summary.blocks_computed == len(BIG_DAMAGED)  # (all found damaged)
    want = {f"levels/{i}/c/{s0}/{s1}/0": 1 for i in range(4) for s0, s1 in [(0, 0), (0, 1)]}
    assert dict(seen.reads) == want, seen.reads.most_common(3)
    assert diff_stores(s, ref) == []


def test_a_rebuilt_shard_is_the_old_one_byte_for_byte(big, tmp_path):
    """``write_small_levels`` given one block's entry, equal to what the store holds, rewrites
    each level's shard to the very bytes it had (the blocks read back in place), for the 16x16,
    the 16x1 and the 1x16 shards."""
    from tiler.resume import JournalEntry

    _, ref, _ = big
    s = Path(shutil.copytree(ref, tmp_path / "s.zarr"))
    loc = Location(str(s))
    meta = read_meta(loc.open_group("r"))
    g = zarr.open_group(s, mode="r")
    for b, region, key in [
        ((5, 7), (0, 16, 0, 16), "c/0/0/0"),
        ((3, 16), (0, 16, 16, 17), "c/0/1/0"),
        ((16, 0), (16, 17, 0, 16), "c/1/0/0"),
    ]:
        levels = [np.asarray(g[f"levels/{i}"][b]) for i in range(4)]
        entry = JournalEntry(levels, exists=True, has_nodata=False, zmin=0, zmax=0, digest=0)
        asm_mod.write_small_levels(loc, meta, {b: entry}, region)
        for i in range(4):
            got = (s / f"levels/{i}" / key).read_bytes()
            assert got == (ref / f"levels/{i}" / key).read_bytes(), (b, i)


# -- 2: the shard flush's journal reads ----------------------------------------------------------

# 150x16 samples in blocks of 9: 19x2 blocks, in shards of 16x2 (two shards)
SMALL = TileOptions(block_size=9, workers=2, executor="threads")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The 19x2-block DEM and its store (the reference)."""
    d = tmp_path_factory.mktemp("audit46_flush")
    src = write_dem(d / "dem.tif", fractal((150, 16), 7))
    return src, tile(src, d / "ref.zarr", SMALL).location.path


def _stop_after(monkeypatch, n: int) -> None:
    """A Ctrl-C in the block after the ``n``-th (``tiler.tile.process_block``)."""
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


def _state(s: Path) -> str | None:
    """The store's ``state`` (None: finished)."""
    return read_meta(zarr.open_group(s, mode="r")).extra.get("state")


@pytest.mark.parametrize("run", ["fresh", "resumed"])
def test_a_damaged_entry_at_a_shard_flush_names_the_block(small, tmp_path, monkeypatch, run):
    """A journal entry damaged between its write and its shard's flush stops the run with
    :class:`StoreCorruptError` naming the block and to rerun (the control, the code before:
    zarr's checksum error); the store stays unfinished, and rerun it computes that block again
    and gives the reference, byte for byte. ``fresh``: the whole shard's entries read at once;
    ``resumed``: a shard begun before the resume, its other entries read together."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    key, block = f"{JOURNAL}/c.3.1.0", "(3, 1)"
    if run == "resumed":  # shard (0, 0) done, and one block of shard (1, 0)
        _stop_after(monkeypatch, 16 * 2 + 1)
        with pytest.raises(KeyboardInterrupt):
            tile(src, dst, SMALL)
        monkeypatch.undo()
        done = {p.name for p in (dst / JOURNAL).glob("c.*")}
        key, block = next(
            (f"{JOURNAL}/c.{r}.{c}.0", f"({r}, {c})")
            for r in range(16, 19)
            for c in range(2)
            if f"c.{r}.{c}.0" not in done
        )
    JournalReads(monkeypatch, dst, damage=[key])
    with pytest.raises(StoreCorruptError, match="rerun the same command") as info:
        tile(src, dst, SMALL)
    msg = str(info.value)
    assert f"block {block}" in msg and "damaged" in msg and str(dst) in msg, msg
    assert _state(dst) == "tiling"
    monkeypatch.undo()
    store = tile(src, dst, SMALL)
    assert store.tile_summary.resumed
    assert diff_stores(dst, ref) == []


def test_the_cli_exits_1_on_a_damaged_entry_at_a_flush(small, tmp_path, monkeypatch):
    """``terrastream tile`` whose flush finds a damaged journal entry exits 1 with one line
    naming the block and saying to rerun (the control, the code before: zarr's checksum error,
    exit 2 as a ``ValueError``)."""
    from typer.testing import CliRunner

    from cli.main import app

    src, _ = small
    dst = tmp_path / "s.zarr"
    JournalReads(monkeypatch, dst, damage=[f"{JOURNAL}/c.3.1.0"])
    args = ["tile", str(src), str(dst), "--block-size", "9", "--workers", "2"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1, res.output
    assert "block (3, 1)" in res.output and "rerun the same command" in res.output, res.output


def test_a_transport_error_at_a_shard_flush_stops_the_run(small, tmp_path, monkeypatch):
    """A connection dropped on both reads of a journal entry at its shard's flush stops the
    run with :class:`StoreUnavailableError` naming the store and to rerun (the control, the
    code before: the raw ``ConnectionResetError``); rerun, it finishes to the reference."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    key = f"{JOURNAL}/c.3.1.0"
    seen = JournalReads(monkeypatch, dst, fail={key: 2})
    with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
        tile(src, dst, SMALL)
    assert str(dst) in str(info.value) and "connection reset" in str(info.value)
    assert seen.failed[key] == 2 and _state(dst) == "tiling"
    monkeypatch.undo()
    store = tile(src, dst, SMALL)
    assert store.tile_summary.resumed
    assert diff_stores(dst, ref) == []


def test_a_shard_flush_reads_again_a_read_dropped_once(small, tmp_path, monkeypatch, caplog):
    """The normal case: a connection dropped once at a flush is read again (with a warning)
    and the run finishes (the control, the code before: the run failed); every entry is read
    once (plus the one retried), and the store is the reference, byte for byte."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    key = f"{JOURNAL}/c.3.1.0"
    seen = JournalReads(monkeypatch, dst, fail={key: 1})
    with caplog.at_level("WARNING", logger="tiler.tile"):
        tile(src, dst, SMALL)
    assert seen.failed[key] == 1 and "trying again" in caplog.text
    assert len(seen.reads) == 19 * 2 and not seen.absent
    assert diff_stores(dst, ref) == []


def test_a_flush_with_no_fault_reads_each_entry_once(small, tmp_path, monkeypatch):
    """The normal case: no fault, no warning; each journal entry read once, none absent."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    seen = JournalReads(monkeypatch, dst)
    tile(src, dst, SMALL)
    assert dict(seen.reads) == {f"{JOURNAL}/c.{r}.{c}.0": 1 for r in range(19) for c in range(2)}
    assert diff_stores(dst, ref) == []


# -- 3: an interrupted repair's journal, listed ---------------------------------------------------

SMALL_REPAIR = TileOptions(block_size=9, workers=1, executor="threads", repair=True)
#: damaged blocks of the small store (their level-0 chunk): three in shard (0, 0), one in (1, 0)
SMALL_DAMAGED = [(2, 1), (3, 0), (5, 0), (17, 1)]


@pytest.fixture(scope="module")
def small_damaged(small, tmp_path_factory):
    """A copy of the small store with :data:`SMALL_DAMAGED` damaged."""
    _, ref = small
    damaged = Path(shutil.copytree(ref, tmp_path_factory.mktemp("audit46_list") / "d.zarr"))
    for br, bc in SMALL_DAMAGED:
        shard = damaged / "levels/0/c" / str(br // 16) / "0" / "0"
        _flip_inner(shard, 16 * 2, (br % 16) * 2 + bc)
    assert verify_store(damaged).bad_blocks == set(SMALL_DAMAGED)
    return damaged


def _interrupted_repair(monkeypatch, small, damaged: Path, dst: Path) -> set[str]:
    """A copy of ``damaged`` whose repair stopped after two blocks (state ``repair``); returns
    the journal keys it holds."""
    src, _ = small
    shutil.copytree(damaged, dst)
    _stop_after(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        tile(src, dst, SMALL_REPAIR)
    monkeypatch.undo()
    assert _state(dst) == "repair"
    return {f"{JOURNAL}/{p.name}" for p in (dst / JOURNAL).glob("c.*")}


def test_a_resumed_repair_reads_only_the_entries_listed(
    small, small_damaged, tmp_path, monkeypatch
):
    """Finishing an interrupted repair asks for no journal key that is not there (the control,
    the code before: all 38, 36 absent); it reads each entry there once, and the store is the
    reference, byte for byte."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    before = _interrupted_repair(monkeypatch, small, small_damaged, dst)
    assert len(before) == 2
    seen = JournalReads(monkeypatch, dst)
    store = tile(src, dst, SMALL_REPAIR)
    assert store.tile_summary.blocks_skipped == 2
    assert not seen.absent, seen.absent
    assert dict(seen.reads) == {f"{JOURNAL}/c.{r}.{c}.0": 1 for r, c in SMALL_DAMAGED}
    assert _state(dst) is None and diff_stores(dst, ref) == []


def test_a_store_that_cannot_list_reads_every_entry(small, small_damaged, tmp_path, monkeypatch):
    """Where the store cannot list (``NotImplementedError``), every journal key is read, as
    before, and the repair finishes to the reference."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    _interrupted_repair(monkeypatch, small, small_damaged, dst)

    def cannot(self, prefix=""):
        raise NotImplementedError("simulated: no listing")

    monkeypatch.setattr(Location, "list_keys", cannot)
    seen = JournalReads(monkeypatch, dst)
    store = tile(src, dst, SMALL_REPAIR)
    assert store.tile_summary.blocks_skipped == 2
    assert sum(seen.absent.values()) == 19 * 2 - 2
    assert _state(dst) is None and diff_stores(dst, ref) == []


@pytest.mark.parametrize("failures", [2, 1])
def test_a_transport_error_listing_the_journal(
    small, small_damaged, tmp_path, monkeypatch, caplog, failures
):
    """A listing the transport fails twice stops the repair with
    :class:`StoreUnavailableError` naming the store (the state stays ``repair``; rerun, it
    finishes to the reference); failing once, it is listed again (the normal case)."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    _interrupted_repair(monkeypatch, small, small_damaged, dst)
    monkeypatch.setattr(journal_mod, "JOURNAL_RETRY_WAIT_S", 0.0)
    real = Location.list_keys
    calls = Counter()

    def flaky(self, prefix=""):
        if prefix == JOURNAL:
            calls[prefix] += 1
            if calls[prefix] <= failures:
                raise ConnectionResetError("simulated: connection reset listing")
        return real(self, prefix)

    monkeypatch.setattr(Location, "list_keys", flaky)
    if failures == 2:
        with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
            tile(src, dst, SMALL_REPAIR)
        assert str(dst) in str(info.value) and "connection reset" in str(info.value)
        assert calls[JOURNAL] == 2 and _state(dst) == "repair"
        monkeypatch.undo()
        tile(src, dst, SMALL_REPAIR)
    else:
        with caplog.at_level("WARNING", logger="tiler.tile"):
            store = tile(src, dst, SMALL_REPAIR)
        assert calls[JOURNAL] == 2 and "trying again" in caplog.text
        assert store.tile_summary.blocks_skipped == 2
    assert _state(dst) is None and diff_stores(dst, ref) == []


@pytest.mark.parametrize("kind", ["local", "memory-url", "zarr-store"])
def test_the_journal_listing_on_each_store_kind(tmp_path, kind):
    """:func:`listed_journal_blocks` finds exactly the entries written, on a local directory,
    an fsspec URL and a zarr Store object, skipping the journal's metadata and a leftover
    temporary file."""
    from tiler.resume import listed_journal_blocks

    target = {
        "local": str(tmp_path / "j.zarr"),
        "memory-url": f"memory://audit46-list-{tmp_path.name}/j.zarr",
        "zarr-store": zarr.storage.MemoryStore(),
    }[kind]
    loc = Location(target)
    g = loc.open_group("w")
    create_journal(g, 3, 4, 3, "int16")
    arr = g[JOURNAL]
    written = [(0, 1), (2, 3), (1, 0)]
    for b in written:
        arr[b] = np.full(arr.shape[2], 1, np.uint8)
    loc.put_bytes(f"{JOURNAL}/c.1.2.0.partial", b"torn")
    assert listed_journal_blocks(loc, arr, loc.url) == sorted(written)
