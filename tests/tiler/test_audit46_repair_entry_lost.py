"""A journal entry the repair wrote that reads back missing or damaged when the repair patches
it in said only "repair of block (r, c) did not complete"; it names the store, says what
happened and to rerun, and the rerun finishes the repair byte-identical."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal, write_dem

import tiler.journal_reads as journal_reads
from tiler.errors import StoreCorruptError
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

sys.path.insert(0, str(Path(__file__).resolve().parent))
from storetools import chunk_files, diff_stores  # noqa: E402


def _opts(**kw) -> TileOptions:
    return TileOptions(block_size=65, workers=1, executor="threads", **kw)


@pytest.mark.parametrize("lost", [True, False], ids=["entry-lost", "control"])
def test_a_lost_repair_entry_says_what_to_do_and_the_rerun_finishes(tmp_path, monkeypatch, lost):
    src = write_dem(tmp_path / "dem.tif", fractal((200, 200), 7))
    ref = tile(src, tmp_path / "ref.zarr", _opts()).location.path
    s = tile(src, tmp_path / "s.zarr", _opts()).location.path
    f = chunk_files(s, "levels/6")[4]
    f.write_bytes(f.read_bytes()[:-3] + b"xyz")  # one block damaged
    real = journal_reads.read_journal_blocks

    def zeroed(jarr, blocks, url=None, damaged=None):
        raw = real(jarr, blocks, url)
        return np.zeros_like(raw)  # as a damaged or unwritten entry reads

    if lost:
        monkeypatch.setattr(journal_reads, "read_journal_blocks", zeroed)
        with pytest.raises(StoreCorruptError) as e:
            tile(src, s, _opts(repair=True))
        msg = str(e.value)
        assert str(s) in msg and "rerun the same command" in msg and "did not keep" in msg
        assert verify_store(s).state == "repair"
        monkeypatch.setattr(journal_reads, "read_journal_blocks", real)
    tile(src, s, _opts(repair=True))  # (the control: repaired at once)
    assert verify_store(s).ok
    assert diff_stores(s, ref) == []
