"""Two writers at once: the second is refused. Re-tiling with overwrite under an open reader:
the reader gets a StoreChangedError or old data, never a mix."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
from demtools import fractal, write_dem
from faults import LONG, record

from tiler.errors import StoreError
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

pytestmark = pytest.mark.reliability

WRITER = textwrap.dedent(
    """
    import sys
    from tiler.errors import StoreError
    from tiler.tile import TileOptions, tile

    if __name__ == "__main__":
        try:
            tile(sys.argv[1], sys.argv[2], TileOptions(block_size=17, workers=1,
                 executor="threads", overwrite=sys.argv[3] == "1"))
        except StoreError as exc:
            print("REFUSED", exc, file=sys.stderr)
            sys.exit(3)
    """
)


def _spawn(tmp_path, src, dst, overwrite=False):
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    return subprocess.Popen(
        [sys.executable, str(script), str(src), str(dst), "1" if overwrite else "0"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_two_writers_second_refused(tmp_path):
    a = write_dem(tmp_path / "a.tif", fractal((130, 130), 1))
    b = write_dem(tmp_path / "b.tif", fractal((130, 130), 2))
    dst = tmp_path / "s.zarr"
    pa = _spawn(tmp_path, a, dst)
    pb = _spawn(tmp_path, b, dst)
    errs = [pa.communicate(timeout=120)[1], pb.communicate(timeout=120)[1]]
    ra, rb = pa.returncode, pb.returncode
    assert sorted([ra, rb]) == [0, 3], errs
    loser = errs[[ra, rb].index(3)]
    assert "being written by process" in loser or "already holds a finished store" in loser
    winner = [a, b][[ra, rb].index(0)]
    assert verify_store(dst, source=winner).ok  # every block from the winner's source
    record("two writers", injected=1, detected=1, lost=0)


@pytest.mark.parametrize("round_", range(5 if LONG else 1))
def test_overwrite_under_an_open_reader(tmp_path, round_):
    a = write_dem(tmp_path / "a.tif", fractal((130, 130), 3))
    b = write_dem(tmp_path / "b.tif", fractal((130, 130), 4))
    dst = tmp_path / "s.zarr"
    tile(a, dst, TileOptions(block_size=17, executor="threads"))
    tile(a, tmp_path / "old.zarr", TileOptions(block_size=17, executor="threads"))
    old = open_store(tmp_path / "old.zarr")
    reader = open_store(dst)
    blocks = list(reader.grid.blocks())
    stats = {"reads": 0, "old": 0, "mixed": 0, "errors": 0}
    stop = threading.Event()

    def read_loop():
        i = 0
        while not stop.is_set():
            b = blocks[i % len(blocks)]
            i += 1
            try:
                got = reader.read_block(b)
            except StoreError:
                stats["errors"] += 1
                return
            stats["reads"] += 1
            stats["old" if np.array_equal(got, old.read_block(b)) else "mixed"] += 1

    t = threading.Thread(target=read_loop, name="test-reader")
    t.start()
    p = _spawn(tmp_path, b, dst, overwrite=True)
    _, err = p.communicate(timeout=120)
    t.join(timeout=30)
    stop.set()
    t.join(timeout=30)
    assert p.returncode == 0, err
    assert stats["mixed"] == 0 and stats["reads"] > 0, stats
    if not stats["errors"]:  # the reader finished its loop before the swap: it must error now
        with pytest.raises(StoreError, match="replaced or rewritten"):
            reader.read_block(blocks[0])
    assert verify_store(dst, source=b).ok
    record("overwrite under reader", injected=1, detected=1, lost=0, **stats)
