"""A remote reader open across a ``tile --repair``: the repair rebuilds a block of a shard, so
every later chunk of the shard moves, and a shard index the reader kept points at another
block's chunk (which passes its own crc32c). The reader read block C's level 0 as block B's
values after a repair, without an error; the repair now writes a new revision of the root
metadata, and a reader that sees it drops its kept shard indexes before its next read.
"""

from __future__ import annotations

import sys
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
from demtools import fractal, write_dem
from rangeserver import LoopbackServer

import tiler.store as store_mod
from tiler.store import open_store
from tiler.tile import TileOptions, tile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from storetools import diff_stores  # noqa: E402


def _drop_inner_chunk(shard: Path, n_inner: int) -> tuple[int, int]:
    """Remove the first inner chunk (on disk) from a shard, compacting the rest, as a shard
    written without it; returns (that chunk's index, the next chunk's index)."""
    data = shard.read_bytes()
    n_idx = n_inner * 16 + 4
    idx = np.frombuffer(data[-n_idx:-4], "<u8").reshape(-1, 2).copy()
    order = [int(i) for i in np.argsort(idx[:, 0])]
    out, new = bytearray(), np.full_like(idx, np.iinfo(np.uint64).max)
    for i in order[1:]:
        off, nb = (int(v) for v in idx[i])
        new[i] = (len(out), nb)
        out += data[off : off + nb]
    body = new.astype("<u8").tobytes()
    shard.write_bytes(bytes(out) + body + google_crc32c.value(body).to_bytes(4, "little"))
    return order[0], order[1]


@pytest.mark.parametrize("fixed", [True, False], ids=["repair-seen", "control-stale-index"])
def test_a_reader_open_across_a_repair_reads_the_repaired_store(tmp_path, monkeypatch, fixed):
    src = write_dem(tmp_path / "dem.tif", fractal((129, 129), 3))
    s = tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, workers=1)).location.path
    ref = tmp_path / "ref.zarr"
    tile(src, ref, TileOptions(block_size=17, workers=1))
    rows, cols = open_store(s).grid.shape
    b, c = _drop_inner_chunk(s / "levels/0/c/0/0/0", rows * cols)
    bb, bc = divmod(b, cols), divmod(c, cols)
    truth = open_store(ref).read_level_raw(bc, 0)
    monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 1e9)  # (checked when asked)
    with LoopbackServer(tmp_path) as url:
        reader = open_store(f"{url}/s.zarr")
        assert np.array_equal(reader.read_level_raw(bc, 0), truth)  # (its index is kept)
        tile(src, s, TileOptions(block_size=17, workers=1, repair=True))
        assert diff_stores(s, ref) == []
        if fixed:
            monkeypatch.setattr(store_mod, "REMOTE_CHECK_INTERVAL_S", 0.0)
        after = reader.read_level_raw(bc, 0)
    if fixed:
        assert np.array_equal(after, truth)
    else:  # the control: with the change unseen, the kept index reads another block
        assert not np.array_equal(after, truth), (bb, bc)
