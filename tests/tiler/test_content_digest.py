"""Content digests (``index/content``, :mod:`tiler.content`): chunks that pass their crc32c but
are not this block's — moved from another block, copied from another store of the same shape,
decoded under another index row — are found by ``verify`` and repaired.

Before them, every case below verified ``ok`` (exit 0) and ``export`` wrote another DEM. Each
test damages a store on purpose (the positive control) beside the pristine store verifying
clean with every digest recomputed.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr
from demtools import fractal, write_dem
from storetools import chunk_files, diff_stores

from tiler import tile as tile_mod
from tiler.content import (
    CONTENT_KEY,
    FOLD_SEED,
    content_digest,
    fold,
    fold_parts,
    part_digest,
)
from tiler.layout import level_size
from tiler.resume import JournalEntry, entry_nbytes, pack, unpack
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


def _opts(block_size: int = 65, **kw) -> TileOptions:
    return TileOptions(block_size=block_size, workers=1, executor="threads", **kw)


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    d = tmp_path_factory.mktemp("content")
    a = fractal((257, 257), 1)
    a[100:120, 10:30] = -9999  # a nodata hole: masks too
    return (write_dem(d / "a.tif", a, nodata=-9999),
            write_dem(d / "b.tif", fractal((257, 257), 2), nodata=-9999))  # fmt: skip


@pytest.fixture(scope="module")
def stores(dems, tmp_path_factory):
    d = tmp_path_factory.mktemp("stores")
    out = {}
    for name, src, bs, kw in [("a", dems[0], 65, {}), ("b", dems[1], 65, {}),
                              ("a17", dems[0], 17, {}), ("b17", dems[1], 17, {})]:  # fmt: skip
        out[name] = tile(src, d / f"{name}.zarr", _opts(bs, **kw)).location.path
    return out


def _copy(stores, name, tmp_path):
    dst = tmp_path / f"{name}.zarr"
    shutil.copytree(stores[name], dst)
    return dst


def _bad(path) -> set:
    rep = verify_store(path)
    assert rep.content_checked
    return {p.block for p in rep.problems if p.array == "index/content"}


def test_the_pristine_stores_verify_with_every_digest(stores, dems):
    for name in ("a", "a17"):
        rep = verify_store(stores[name], source=dems[0])
        assert rep.ok and rep.content_checked, rep.problems


def test_two_level_chunks_swapped_are_found_and_repaired(stores, dems, tmp_path):
    s = _copy(stores, "a", tmp_path)
    x, y = s / "levels/6/c/0/0/0", s / "levels/6/c/0/1/0"
    bx, by = x.read_bytes(), y.read_bytes()
    x.write_bytes(by)
    y.write_bytes(bx)
    assert _bad(s) == {(0, 0), (0, 1)}
    tile(dems[0], s, _opts(repair=True))
    assert verify_store(s).ok and diff_stores(s, stores["a"]) == []


@pytest.mark.parametrize(("store", "other", "array"), [
    ("a", "b", "levels/0"),     # one shard holds every block's level 0
    ("a17", "b17", "levels/2"),  # a many-shard store: one of its shards
    ("a", "b", "errors"),
    ("a", "b", "levels/6"),
])  # fmt: skip
def test_a_chunk_from_another_store_is_found(stores, tmp_path, store, other, array):
    s = _copy(stores, store, tmp_path)
    victim = chunk_files(s, array)[0]
    victim.write_bytes((stores[other] / victim.relative_to(s)).read_bytes())
    bad = _bad(s)
    assert bad, f"{array} from store {other!r} not found"
    assert all(p.array == "index/content" for p in verify_store(s).problems)


@pytest.mark.parametrize(("name", "value"), [("zmax", 1.0), ("exists", False),
                                             ("has_nodata", True), ("digest", 7)])  # fmt: skip
def test_an_index_value_rewritten_with_a_valid_checksum_is_found(stores, tmp_path, name, value):
    s = _copy(stores, "a", tmp_path)
    arr = zarr.open_array(s / "index" / name, mode="r+")
    block = (1, 1) if name != "has_nodata" else (3, 3)
    assert arr[block] != value
    arr[block] = value  # (zarr writes a new chunk: its crc32c is right)
    assert block in {p.block for p in verify_store(s).problems}


def test_a_store_tiled_without_content_digests_still_verifies(dems, tmp_path, monkeypatch):
    """A store tiled before content digests has no ``index/content``: verify checks what it
    can and says it did not check them."""
    monkeypatch.setattr(tile_mod, "CONTENT_SCHEME", None)
    s = tile(dems[0], tmp_path / "old.zarr", _opts()).location.path
    assert not (s / "index" / "content").exists()
    rep = verify_store(s)
    assert rep.ok and not rep.content_checked
    from typer.testing import CliRunner

    from cli.main import app

    out = CliRunner().invoke(app, ["verify", str(s)]).output
    assert "ok" in out and "content digests: none" in out, out
    assert (
        CONTENT_KEY not in zarr.open_group(s).attrs["terrastream"]
        or not zarr.open_group(s).attrs["terrastream"][CONTENT_KEY]
    )


def test_journal_rows_with_and_without_content_round_trip():
    k = 2
    levels = [np.arange(level_size(i), dtype=np.int16) for i in range(k + 1)]
    e = JournalEntry(levels, True, False, 1.5, 9.0, 42, content=2**63 + 5)
    raw = pack(e, "int16")
    assert raw.size == entry_nbytes(k, "int16")
    back = unpack(raw, k, "int16")
    assert back.content == e.content and back.digest == 42
    old = pack(e, "int16", content=False)  # a journal begun before content digests
    assert old.size == entry_nbytes(k, "int16", content=False) < raw.size
    back = unpack(old, k, "int16")
    assert back.content is None and back.digest == 42 and back.zmax == 9.0


def test_the_digest_ties_content_to_its_block_and_row():
    v = np.arange(16, dtype=np.int16)
    parts = [part_digest(v, "int16"), part_digest(v[::-1], "int16"), part_digest(None, bool)]
    f = fold_parts(parts)
    d = content_digest((0, 0), f, True, False, 1.0, 2.0, 3)
    assert d == content_digest((0, 0), fold_parts(list(parts)), True, False, 1.0, 2.0, 3)
    assert d != content_digest((0, 1), f, True, False, 1.0, 2.0, 3)  # another block
    assert d != content_digest((0, 0), fold_parts(parts[::-1]), True, False, 1.0, 2.0, 3)
    assert d != content_digest((0, 0), f, True, False, 1.0, 2.5, 3)  # another row
    nan = content_digest((0, 0), f, False, True, float("nan"), float("nan"), 0)
    assert nan == content_digest((0, 0), f, False, True, -float("nan"), float("nan"), 0)
    assert part_digest(v, "int16") != part_digest(v.astype(np.int32), "int32")
    assert part_digest(v, ">i2") == part_digest(v, "<i2")  # values, not their byte order
    acc = FOLD_SEED  # folding as a reader reads equals folding the list
    for p in parts:
        acc = fold(acc, p)
    assert acc == f


def test_a_repair_that_mends_nothing_is_an_error(dems, stores, tmp_path, monkeypatch):
    """A store without content digests whose digest table was copied from another store:
    ``verify`` reports the source checksum but no block, and ``tile --repair`` exited 0 having
    changed nothing (``verify`` still failing: a loop). It now says no block rebuild mends it."""
    from tiler.errors import StoreCorruptError

    monkeypatch.setattr(tile_mod, "CONTENT_SCHEME", None)
    s = tile(dems[0], tmp_path / "old.zarr", _opts()).location.path
    for f in chunk_files(s, "index/digest"):
        f.write_bytes((stores["b"] / f.relative_to(s)).read_bytes())
    rep = verify_store(s)
    assert not rep.ok and not rep.bad_blocks
    with pytest.raises(StoreCorruptError, match="no block rebuild repairs.*--overwrite|overwrite"):
        tile(dems[0], s, _opts(repair=True))


def test_a_repair_of_bad_blocks_still_succeeds(stores, dems, tmp_path):
    """The control: a repair with blocks to rebuild runs, and leaves a new revision."""
    s = _copy(stores, "a", tmp_path)
    victim = chunk_files(s, "levels/6")[3]
    victim.unlink()
    tile(dems[0], s, _opts(repair=True))
    assert verify_store(s).ok
    assert zarr.open_group(s).attrs["terrastream"].get("revision")
