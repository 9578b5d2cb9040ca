"""Flip random bits in, and delete, random chunks of every array kind: every fault is detected.

A store of 3x3 blocks of 65² (levels 0-5 sharded, level 6 not), with a nodata hole (masks), is
damaged one chunk at a time. Each fault must make reading raise a store error (reading = opening
the store, its index, every block's levels, errors and masks, as ``export`` and the streamer do)
or, for the two derived tables the reader never uses, be found by ``verify_store``; and
``verify_store`` must find every fault. A sample of faults is repaired from the source and the
store must then be byte-identical to the pristine one.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from demtools import fractal, write_dem
from faults import LONG, SEED, record
from storetools import chunk_files, diff_stores, flip_bit  # after faults (sys.path)

from tiler.errors import StoreError
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

KINDS = [
    "levels/0",
    "levels/3",
    "levels/5",
    "levels/6",
    "errors",
    "mask",
    "index/exists",
    "index/done",
    "index/has_nodata",
    "index/zmin",
    "index/zmax",
    "index/digest",
    "index/window",
    "index/content",
    "level_index",
    "order_index",
]
#: no reader uses them (derived tables, content digests): verify must find their damage
TABLES = ("level_index", "order_index", "index/content")
pytestmark = pytest.mark.reliability
OPTS = TileOptions(block_size=65, workers=1, executor="threads")


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    d = tmp_path_factory.mktemp("pristine")
    data = fractal((150, 150), 42)
    data[70:80, 10:20] = -9999
    src = write_dem(d / "dem.tif", data, nodata=-9999)
    tile(src, d / "s.zarr", OPTS)
    return src, d / "s.zarr"


def read_everything(path: Path) -> list:
    """What a reading command reads; raises on any detected damage."""
    s = open_store(path)
    idx = s.index
    out = [idx.exists.copy(), idx.zmin.copy(), idx.digest.copy(), idx.window.copy()]
    for b in s.grid.blocks():
        out.append(s.read_block(b))
        out.extend(s.read_errors(b).values().__iter__().__next__())
        if idx.has_nodata[b]:
            out.append(s.read_mask(b))
    return out


def _same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in zip(a, b, strict=True)
    )


def _run_faults(pristine, tmp_path, mode: str, trials: int) -> dict:
    src, clean = pristine
    reference = read_everything(clean)
    rng = np.random.default_rng(SEED + (mode == "delete"))
    counts = {"injected": 0, "detected_by_read": 0, "detected_by_verify": 0, "survived": 0}
    counts["lost"] = counts["repaired"] = 0
    n_repairs = 6 if LONG else 2
    for kind in KINDS:
        for t in range(trials):
            work = tmp_path / f"{kind.replace('/', '_')}-{t}.zarr"
            shutil.copytree(clean, work)
            files = chunk_files(work, kind)
            assert files, kind
            victim = files[int(rng.integers(len(files)))]
            if mode == "flip":
                flip_bit(victim, rng)
            else:
                victim.unlink()
            counts["injected"] += 1
            try:
                got = read_everything(work)
            except StoreError:
                counts["detected_by_read"] += 1
            else:
                if kind not in TABLES:
                    counts["lost" if not _same(got, reference) else "survived"] += 1
                    pytest.fail(f"{mode} in {victim} was not detected by reading")
            rep = verify_store(work)
            assert not rep.ok, f"{mode} in {victim} not found by verify"
            counts["detected_by_verify"] += 1
            if counts["repaired"] < n_repairs and rng.random() < 0.3:
                tile(src, work, TileOptions(block_size=65, repair=True, executor="threads"))
                assert verify_store(work).ok
                assert diff_stores(work, clean) == [], victim
                counts["repaired"] += 1
            shutil.rmtree(work)
    return counts


def test_valid_chunks_swapped_within_an_array_are_found_by_verify(pristine, tmp_path):
    """Two valid chunks of one array swapped pass every crc32c (a read returns another block's
    data): ``verify``'s content digests find both blocks, and a repair restores the store."""
    src, clean = pristine
    rng = np.random.default_rng(SEED + 2)
    counts = {"injected": 0, "detected_by_verify": 0, "repaired": 0}
    for kind in KINDS:
        files = chunk_files(clean, kind)
        if len(files) < 2:
            continue  # (one shard, one index chunk: nothing to swap with)
        for t in range(3 if LONG else 1):
            work = tmp_path / f"swap-{kind.replace('/', '_')}-{t}.zarr"
            shutil.copytree(clean, work)
            i, j = rng.choice(len(files), size=2, replace=False)
            a, b = (work / files[k].relative_to(clean) for k in (i, j))
            da, db = a.read_bytes(), b.read_bytes()
            if da == db:
                shutil.rmtree(work)
                continue
            a.write_bytes(db)
            b.write_bytes(da)
            counts["injected"] += 1
            rep = verify_store(work)
            assert not rep.ok and len(rep.bad_blocks) >= 2, f"swap in {kind} not found"
            counts["detected_by_verify"] += 1
            if t == 0:
                tile(src, work, TileOptions(block_size=65, repair=True, executor="threads"))
                assert verify_store(work).ok and diff_stores(work, clean) == []
                counts["repaired"] += 1
            shutil.rmtree(work)
    record("valid chunks swapped", **counts)
    assert counts["injected"] >= 2 and counts["detected_by_verify"] == counts["injected"]


def test_quiet_store_reads_and_verifies_clean(pristine):
    src, clean = pristine
    read_everything(clean)
    rep = verify_store(clean, source=src)
    assert rep.ok and rep.chunks_checked > 30


def test_bit_flips_in_every_array_kind_are_detected(pristine, tmp_path):
    counts = _run_faults(pristine, tmp_path, "flip", 6 if LONG else 2)
    record("bit flips", **counts)
    assert counts["detected_by_verify"] == counts["injected"]
    assert counts["lost"] == 0


def test_deleted_chunks_of_every_array_kind_are_detected(pristine, tmp_path):
    counts = _run_faults(pristine, tmp_path, "delete", 3 if LONG else 1)
    record("deleted chunks", **counts)
    assert counts["detected_by_verify"] == counts["injected"]
    assert counts["lost"] == 0
