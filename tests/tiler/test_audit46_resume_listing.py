"""Resuming a tiling lists the journal (audit 46, as finishing a repair does).

Resuming an unfinished tiling read the journal a shard region at a time, which asks the store
for every entry key, those of the blocks not done too (on S3 through s3fs a HEAD 404 and a
LIST each: 3,200 requests for a 40x40 journal). It now lists the journal's keys once and reads
only the entries there, a shard's fetched together; a store that cannot list is read as
before. The resumed store is an uninterrupted run's, byte for byte.
"""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path

import pytest
import zarr
import zarr.storage
from demtools import fractal, write_dem
from storetools import JournalReads, diff_stores

import tiler.tile as tile_mod
from tiler.errors import StoreUnavailableError
from tiler.location import Location
from tiler.meta import read_meta
from tiler.resume import JOURNAL
from tiler.tile import TileOptions, tile

# 150x16 samples in blocks of 9: 19x2 blocks, in shards of 16x2 (two shards)
OPTS = TileOptions(block_size=9, workers=2, executor="threads")
ALL = {f"{JOURNAL}/c.{r}.{c}.0" for r in range(19) for c in range(2)}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The 19x2-block DEM and its store tiled uninterrupted (the reference)."""
    d = tmp_path_factory.mktemp("audit46_resume_list")
    src = write_dem(d / "dem.tif", fractal((150, 16), 7))
    return src, tile(src, d / "ref.zarr", OPTS).location.path


def _interrupted(monkeypatch, src, dst: Path, n: int = 16 * 2 + 1) -> set[str]:
    """Tile ``src`` to ``dst`` with a Ctrl-C in the block after the ``n``-th (by default:
    shard (0, 0) all done, shard (1, 0) begun); return the journal keys left."""
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
    monkeypatch.undo()
    assert read_meta(zarr.open_group(dst, mode="r")).extra.get("state") == "tiling"
    return {f"{JOURNAL}/{p.name}" for p in (dst / JOURNAL).glob("c.*")}


@pytest.mark.parametrize("n", [1, 16 * 2 + 1])
def test_a_resumed_tiling_asks_for_no_absent_journal_key(small, tmp_path, monkeypatch, n):
    """A resumed tiling asks for no journal key that is not there (the control, the code
    before: one look for each block not done); every entry is read once over the
    whole run (the done ones at the resume, the others at their shard's flush), and the store
    is the uninterrupted run's, byte for byte. ``n`` 33: shard (0, 0) all done, written during
    the resume's scan; ``n`` 1: shard (0, 0) begun only."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    before = _interrupted(monkeypatch, src, dst, n)
    assert 0 < len(before) < len(ALL)
    seen = JournalReads(monkeypatch, dst)
    store = tile(src, dst, OPTS)
    assert store.tile_summary.resumed
    assert store.tile_summary.blocks_skipped == len(before)
    assert not seen.absent, sorted(seen.absent)
    assert dict(seen.reads) == dict.fromkeys(ALL, 1)
    assert diff_stores(dst, ref) == []


def test_a_store_that_cannot_list_is_read_as_before(small, tmp_path, monkeypatch):
    """Where the store cannot list (``NotImplementedError``), every journal key is asked for,
    a shard region at a time, as before, and the resume finishes to the reference."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    before = _interrupted(monkeypatch, src, dst)

    def cannot(self, prefix=""):
        raise NotImplementedError("simulated: no listing")

    monkeypatch.setattr(Location, "list_keys", cannot)
    seen = JournalReads(monkeypatch, dst)
    store = tile(src, dst, OPTS)
    assert store.tile_summary.blocks_skipped == len(before)
    assert set(seen.absent) == ALL - before
    assert diff_stores(dst, ref) == []


def test_a_damaged_listed_entry_is_computed_again(small, tmp_path, monkeypatch):
    """An entry the listing shows whose crc32c fails is not done: its block is computed again
    (the other entries of its shard kept), and the store is the reference, byte for byte."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    before = _interrupted(monkeypatch, src, dst)
    key = sorted(before)[len(before) // 2]
    seen = JournalReads(monkeypatch, dst, damage=[key])
    store = tile(src, dst, OPTS)
    assert store.tile_summary.blocks_skipped == len(before) - 1
    assert not seen.absent
    assert diff_stores(dst, ref) == []


@pytest.mark.parametrize("where", ["entry", "listing"])
@pytest.mark.parametrize("failures", [2, 1])
def test_a_transport_error_at_the_resume(small, tmp_path, monkeypatch, caplog, where, failures):
    """A read of a listed entry, or the listing, that the transport fails twice stops the
    resume with :class:`StoreUnavailableError` naming the store (the store stays unfinished;
    rerun, it finishes to the reference); failing once, it is tried again with a warning."""
    src, ref = small
    dst = tmp_path / "s.zarr"
    before = _interrupted(monkeypatch, src, dst)
    key = sorted(before)[0]
    calls = Counter()
    if where == "entry":
        seen = JournalReads(monkeypatch, dst, fail={key: failures})
    else:
        seen = JournalReads(monkeypatch, dst)
        real = Location.list_keys

        def flaky(self, prefix=""):
            if prefix == JOURNAL:
                calls[prefix] += 1
                if calls[prefix] <= failures:
                    raise ConnectionResetError("simulated: connection reset listing")
            return real(self, prefix)

        monkeypatch.setattr(Location, "list_keys", flaky)
    if failures == 2:
        with pytest.raises(StoreUnavailableError, match="rerun the same command") as info:
            tile(src, dst, OPTS)
        assert str(dst) in str(info.value) and "connection reset" in str(info.value)
        assert read_meta(zarr.open_group(dst, mode="r")).extra.get("state") == "tiling"
        monkeypatch.undo()
        store = tile(src, dst, OPTS)
    else:
        with caplog.at_level("WARNING", logger="tiler.tile"):
            store = tile(src, dst, OPTS)
        assert "trying again" in caplog.text
        assert seen.failed[key] == 1 or calls[JOURNAL] == 2
    assert store.tile_summary.blocks_skipped == len(before)
    assert diff_stores(dst, ref) == []
