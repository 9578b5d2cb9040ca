"""Format 2: checksummed arrays, dimension names, locations, codecs, info, verify and repair."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
import zarr
from demtools import fractal
from storetools import diff_stores, flip_bit

from tiler import codecs
from tiler.errors import (
    ChunkChecksumError,
    JobMismatchError,
    MissingChunkError,
    StoreChangedError,
    StoreCorruptError,
    StoreError,
    StoreExistsError,
    StoreLockedError,
    StoreVersionError,
    TilingInterrupted,
)
from tiler.info import store_info
from tiler.lease import LEASE_KEY, UNREADABLE_GRACE_S, WriterLease
from tiler.location import Location
from tiler.schema import DEFAULT_CLEVEL
from tiler.store import open_store
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store


def test_every_array_has_crc32c_and_dimension_names(dem_factory, tmp_path):
    tile(dem_factory(fractal((40, 40), 1)), tmp_path / "s.zarr", TileOptions(block_size=17))
    g = zarr.open_group(tmp_path / "s.zarr", mode="r")
    names = [f"levels/{i}" for i in range(5)] + ["errors", "mask", "level_index"]
    names += [f"index/{n}" for n in ("exists", "done", "has_nodata", "zmin", "zmax", "digest")]
    for name in [*names, "index/window", "order_index"]:
        meta = json.loads((tmp_path / "s.zarr" / name / "zarr.json").read_text())
        text = json.dumps(meta["codecs"])
        assert "crc32c" in text, name
        assert meta.get("dimension_names") and None not in meta["dimension_names"], name
        if name in ("levels/0", "levels/4"):  # sharded: inner chunks and the shard index
            assert text.count("crc32c") == 2, name
        assert g[name].shape[0] == (17 if name.endswith("_index") else 3)
    assert not (tmp_path / "s.zarr" / "journal").exists()
    assert not (tmp_path / "s.zarr" / LEASE_KEY).exists()


def test_location_kinds(tmp_path):
    for target in (tmp_path / "x", "memory://loc-test/x", zarr.storage.MemoryStore()):
        loc = Location(target)
        assert not loc.key_exists("a/b")
        loc.put_bytes("a/b", b"1")
        assert loc.get_bytes("a/b") == b"1" and loc.key_exists("a/b")
        assert not loc.put_if_absent("a/b", b"2") and loc.get_bytes("a/b") == b"1"
        assert loc.put_if_absent("a/c", b"3")
        assert loc.list_keys("a") == ["a/b", "a/c"]
        assert loc.total_size("a") == 2
        loc.delete_key("a/b")
        assert loc.get_bytes("a/b") is None
        loc.delete_prefix("a")
        assert loc.list_keys("a") == []
    local = Location(tmp_path / "x")
    assert local.is_local and local.can_rename and local.picklable() == str(tmp_path / "x")
    mem = Location("memory://loc-test/x")
    assert mem.is_memory and not mem.can_share_with_processes
    with pytest.raises(OSError, match="cannot be shared"):
        mem.picklable()


def test_zarr_store_object_as_destination(dem_factory):
    data = fractal((30, 30), 2)
    ms = zarr.storage.MemoryStore()
    store = tile(dem_factory(data), ms, TileOptions(block_size=17))
    np.testing.assert_array_equal(store.read_block((0, 0))[:17, :17], data[:17, :17])
    assert verify_store(ms).ok


def test_codec_registry():
    assert set(codecs.names()) >= {"int-residual", "float-xor"}
    with pytest.raises(StoreVersionError, match="'zfp-9' is unknown"):
        codecs.get("zfp-9")
    rng = np.random.default_rng(0)
    g = rng.integers(-500, 500, (17, 17)).astype(np.int16)
    c = codecs.for_dtype(g.dtype)
    raws = c.encode(g, 4)
    np.testing.assert_array_equal(c.decode_grid(raws, g.dtype, 4), g)


def test_format_1_store_still_reads(dem_factory, tmp_path, monkeypatch):
    import tiler.tile as tile_mod

    data = fractal((40, 40), 3)
    monkeypatch.setattr(tile_mod, "FORMAT_VERSION", 1)
    tile(dem_factory(data), tmp_path / "v1.zarr", TileOptions(block_size=17))
    monkeypatch.undo()
    text = (tmp_path / "v1.zarr" / "errors" / "zarr.json").read_text()
    assert "crc32c" not in text
    s = open_store(tmp_path / "v1.zarr")
    assert s.meta.format_version == 1 and not s.checksummed and not s.direct_reads  # zarr reads
    np.testing.assert_array_equal(s.read_block((1, 1))[:8, :8], data[16:24, 16:24])
    assert store_info(tmp_path / "v1.zarr")["checksums"] == "none (format 1)"
    assert store_info(tmp_path / "v1.zarr")["blocks_with_nodata"] == 0


def test_info_counts_nodata_not_padding(dem_factory, tmp_path):
    data = fractal((40, 40), 4)  # 40 = 2*16+8: the last block row/column is padded
    tile(dem_factory(data), tmp_path / "a.zarr", TileOptions(block_size=17))
    assert store_info(tmp_path / "a.zarr")["blocks_with_nodata"] == 0
    data[5, 5] = -9999
    tile(dem_factory(data, "b.tif", nodata=-9999), tmp_path / "b.zarr", TileOptions(block_size=17))
    info = store_info(tmp_path / "b.zarr")
    assert info["blocks_with_nodata"] == 1 and info["checksums"] == "crc32c on every chunk"


@pytest.mark.parametrize("crs", ["EPSG:32633", "EPSG:4326"])
def test_info_bounds_are_the_rasters_and_extent_its_sample_centres(dem_factory, tmp_path, crs):
    import rasterio
    from typer.testing import CliRunner

    from cli.main import app

    cell, origin = (30.0, (500000.0, 5000000.0)) if crs != "EPSG:4326" else (1 / 1200, (1.0, 43.0))
    src = dem_factory(fractal((40, 50), 4), crs=crs, cell=cell, origin=origin)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    info = store_info(tmp_path / "s.zarr")
    with rasterio.open(src) as ds:
        assert info["bounds"] == pytest.approx(list(ds.bounds), abs=1e-9)
    half = np.array([cell, cell, -cell, -cell]) / 2
    assert info["extent"] == pytest.approx(list(np.array(info["bounds"]) + half), abs=1e-9)
    out = CliRunner().invoke(app, ["info", str(tmp_path / "s.zarr")]).output
    digits = 6 if crs == "EPSG:4326" else 3  # degrees to ~0.1 m, metres to the millimetre
    assert f"bounds         x {info['bounds'][0]:.{digits}f} .. " in out


def test_block_size_larger_than_needed_is_clamped(dem_factory, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        s = tile(
            dem_factory(fractal((20, 20), 5)), tmp_path / "s.zarr", TileOptions(block_size=16385)
        )
    assert s.meta.block_size == 33
    assert "block size 16385 is larger than a 20x20 DEM needs; using 33" in caplog.text
    assert s.tile_summary.notes


def test_quiet_store_verifies_clean(dem_factory, tmp_path):
    src = dem_factory(fractal((40, 40), 6), nodata=None)
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    rep = verify_store(tmp_path / "s.zarr", source=src)
    assert rep.ok and rep.source_checked and rep.chunks_checked > 20, rep.problems


def test_bit_flip_found_named_and_repaired(dem_factory, tmp_path, caplog):
    data = fractal((150, 150), 7)
    src = dem_factory(data)
    opts = TileOptions(block_size=65)
    tile(src, tmp_path / "ref.zarr", opts)
    tile(src, tmp_path / "s.zarr", opts)
    rng = np.random.default_rng(1)
    chunk = tmp_path / "s.zarr" / "levels" / "6" / "c" / "1" / "2" / "0"
    flip_bit(chunk, rng)
    with pytest.raises(ChunkChecksumError, match=r"level 6 of block \(1, 2\)") as ei:
        open_store(tmp_path / "s.zarr").read_block((1, 2))
    assert ei.value.level == 6 and ei.value.block == (1, 2) and ei.value.array == "levels/6"
    rep = verify_store(tmp_path / "s.zarr")
    assert not rep.ok and rep.bad_blocks == {(1, 2)}
    reader = open_store(tmp_path / "s.zarr")  # open across the repair: same generation
    with caplog.at_level(logging.WARNING, logger="tiler"):
        fixed = tile(src, tmp_path / "s.zarr", TileOptions(block_size=65, repair=True))
    assert fixed.tile_summary.blocks_repaired == 1
    said = [r.getMessage() for r in caplog.records if "repairing" in r.getMessage()]
    assert said == [
        f"repairing 1 damaged block(s) of {(tmp_path / 's.zarr').as_posix()} from {src}"
    ]
    np.testing.assert_array_equal(reader.read_block((1, 2)), fixed.read_block((1, 2)))
    assert verify_store(tmp_path / "s.zarr").ok
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def test_a_repair_from_a_source_edited_since_is_refused(dem_factory, tmp_path):
    """`--repair` trusted the job's fingerprint (header, size, three 256² windows): a source
    edited in place elsewhere passed, and the repaired block held the new samples beside
    blocks of the old DEM (exit 0). The bad blocks' source samples are now compared with the
    digests the store recorded. Control: the original source repairs."""
    import rasterio

    data = fractal((700, 700), 7)
    src = dem_factory(data)
    opts = TileOptions(block_size=257)
    tile(src, tmp_path / "s.zarr", opts)
    flip_bit(tmp_path / "s.zarr" / "levels" / "8" / "c" / "1" / "2" / "0", np.random.default_rng(1))
    edited = data.copy()
    edited[260:270, 600:610] += 3  # inside block (1, 2), outside the fingerprint's windows
    with rasterio.open(src, "r+") as ds:
        ds.write(edited, 1)
    with pytest.raises(
        JobMismatchError, match=r"samples of 1 damaged block\(s\) differ .*\(1, 2\)"
    ):
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=257, repair=True))
    assert verify_store(tmp_path / "s.zarr").bad_blocks == {(1, 2)}  # nothing written
    with rasterio.open(src, "r+") as ds:
        ds.write(data, 1)
    fixed = tile(src, tmp_path / "s.zarr", TileOptions(block_size=257, repair=True))
    assert fixed.tile_summary.blocks_repaired == 1 and verify_store(tmp_path / "s.zarr").ok
    # a repair from another file names both files (not the mosaic plan's repr)
    other = dem_factory(fractal((700, 700), 8), "other.tif")
    with pytest.raises(
        JobMismatchError, match=r"store was tiled from '.*dem\.tif', this run reads '.*other\.tif'"
    ):
        tile(other, tmp_path / "s.zarr", TileOptions(block_size=257, repair=True))


def test_missing_chunk_is_an_error_not_fill(dem_factory, tmp_path):
    tile(dem_factory(fractal((40, 40), 8)), tmp_path / "s.zarr", TileOptions(block_size=17))
    (tmp_path / "s.zarr" / "errors" / "c" / "0" / "1" / "0" / "0").unlink()
    s = open_store(tmp_path / "s.zarr")
    with pytest.raises(MissingChunkError, match=r"errors of block \(0, 1\)"):
        s.read_errors((0, 1))
    s.read_errors((0, 0))  # the others still read


def test_missing_array_refused_on_open(dem_factory, tmp_path):
    import shutil

    tile(dem_factory(fractal((40, 40), 9)), tmp_path / "s.zarr", TileOptions(block_size=17))
    shutil.rmtree(tmp_path / "s.zarr" / "levels" / "4")
    with pytest.raises(StoreCorruptError, match="no array 'levels/4'"):
        open_store(tmp_path / "s.zarr")


def test_damaged_array_metadata_refused_on_open(dem_factory, tmp_path):
    """The arrays are opened at once: a damaged one among them is named; a group where an
    array belongs is damage too; the first damaged array in the layout's order is reported."""
    import shutil

    tile(dem_factory(fractal((40, 40), 9)), tmp_path / "s.zarr", TileOptions(block_size=17))
    open_store(tmp_path / "s.zarr")  # the control: the intact store opens
    (tmp_path / "s.zarr" / "errors" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreCorruptError, match="metadata of array 'errors'.* is damaged"):
        open_store(tmp_path / "s.zarr")
    (tmp_path / "s.zarr" / "levels" / "2" / "zarr.json").write_text("[]")
    with pytest.raises(StoreCorruptError, match="'levels/2'"):
        open_store(tmp_path / "s.zarr")
    shutil.rmtree(tmp_path / "s.zarr" / "levels" / "2")
    (tmp_path / "s.zarr" / "levels" / "2").mkdir()
    (tmp_path / "s.zarr" / "levels" / "2" / "zarr.json").write_text(
        '{"zarr_format": 3, "node_type": "group", "attributes": {}}'
    )
    with pytest.raises(StoreCorruptError, match="array 'levels/2' .* damaged.*node_type"):
        open_store(tmp_path / "s.zarr")


def _interrupt(monkeypatch, n):
    import tiler.tile as tile_mod

    real = tile_mod.process_block
    count = {"n": 0}

    def flaky(window, params):
        count["n"] += 1
        if count["n"] > n:
            raise KeyboardInterrupt("simulated Ctrl-C")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", flaky)


def test_ctrl_c_raises_tiling_interrupted_and_resumes_exactly(dem_factory, tmp_path, monkeypatch):
    src = dem_factory(fractal((100, 100), 10))
    opts = TileOptions(block_size=17, workers=1, executor="threads")
    _interrupt(monkeypatch, 11)
    with pytest.raises(TilingInterrupted, match="run the same tile"):
        tile(src, tmp_path / "s.zarr", opts)
    monkeypatch.undo()
    seen = []
    s = tile(src, tmp_path / "s.zarr", opts, progress=seen.append)
    assert s.tile_summary.blocks_skipped == 11 == seen[-1].blocks_skipped
    assert s.tile_summary.blocks_computed == 49 - 11
    tile(src, tmp_path / "ref.zarr", opts)
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


@pytest.mark.parametrize("deferred", [True, False], ids=["deferred", "control"])
def test_ctrl_c_during_the_layout_is_raised_after_it(dem_factory, tmp_path, monkeypatch, deferred):
    """A real SIGINT while the layout is created (zarr's synchronous calls) is raised once the
    layout is written: the store is left in state ``tiling`` and a rerun gives the
    uninterrupted store. Control: without the deferral it lands inside the layout, which is
    left in state ``layout`` (inside zarr's calls it left pending writes on zarr's loop)."""
    import signal

    import tiler.destination as dest

    if not deferred:
        monkeypatch.setattr(dest, "DeferredInterrupt", contextlib.nullcontext)
    real = dest.create_layout

    def interrupted(group, meta, level, **kw):
        signal.raise_signal(signal.SIGINT)  # the handler runs before the next bytecode
        return real(group, meta, level, **kw)

    monkeypatch.setattr(dest, "create_layout", interrupted)
    src = dem_factory(fractal((60, 60), 14))
    opts = TileOptions(block_size=17, workers=1, executor="threads")
    with pytest.raises(TilingInterrupted):
        tile(src, tmp_path / "s.zarr", opts)
    state = json.loads((tmp_path / "s.zarr" / "zarr.json").read_text())
    state = state["attributes"]["terrastream"]["state"]
    assert state == ("tiling" if deferred else "layout")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    monkeypatch.undo()
    tile(src, tmp_path / "s.zarr", opts)
    tile(src, tmp_path / "ref.zarr", opts)
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


@pytest.mark.parametrize("deferred", [True, False], ids=["deferred", "control"])
def test_ctrl_c_during_the_final_writes_lets_them_finish(
    dem_factory, tmp_path, monkeypatch, caplog, deferred
):
    """A real SIGINT while ``finish`` writes the shards and the index (zarr's synchronous
    calls) waits for them: the store is complete and equals an uninterrupted one, with a
    warning. Control: without the deferral it lands inside, and the store is left unfinished."""
    import signal

    import tiler.assemble as asm_mod

    src = dem_factory(fractal((60, 60), 15))
    opts = TileOptions(block_size=17, workers=1, executor="threads")
    tile(src, tmp_path / "ref.zarr", opts)  # uninterrupted
    if not deferred:
        monkeypatch.setattr(
            asm_mod, "DeferredInterrupt", lambda **kw: contextlib.nullcontext(_NoFlag())
        )
    real = asm_mod.finish

    def interrupted(*a, **kw):
        signal.raise_signal(signal.SIGINT)  # the handler runs before the next bytecode
        return real(*a, **kw)

    monkeypatch.setattr(asm_mod, "finish", interrupted)
    if deferred:
        with caplog.at_level(logging.WARNING, logger="tiler.tile"):
            tile(src, tmp_path / "s.zarr", opts)
        assert "Ctrl-C during the final writes" in caplog.text
        assert open_store(tmp_path / "s.zarr").meta.complete
        assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []
    else:
        with pytest.raises(TilingInterrupted):
            tile(src, tmp_path / "s.zarr", opts)
        doc = json.loads((tmp_path / "s.zarr" / "zarr.json").read_text())
        assert doc["attributes"]["terrastream"]["complete"] is False
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


class _NoFlag:
    interrupted = False


def test_resume_with_other_source_or_option_refused(dem_factory, tmp_path, monkeypatch):
    a = dem_factory(fractal((60, 60), 11), "a.tif")
    b = dem_factory(fractal((60, 60), 12), "b.tif")
    opts = TileOptions(block_size=17, workers=1, executor="threads")
    _interrupt(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        tile(a, tmp_path / "s.zarr", opts)
    monkeypatch.undo()
    # the message names both files (a fingerprint alone names none)
    with pytest.raises(
        JobMismatchError,
        match=r"source: store was tiled from '.*a\.tif', this run reads '.*b\.tif'",
    ):
        tile(b, tmp_path / "s.zarr", opts)
    with pytest.raises(
        JobMismatchError, match=f"compression_level: store has {DEFAULT_CLEVEL}, this run has 7"
    ):
        tile(a, tmp_path / "s.zarr", TileOptions(block_size=17, compression_level=7))
    tile(a, tmp_path / "s.zarr", opts)  # the original job still finishes
    _interrupt(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        tile(a, tmp_path / "t.zarr", opts)
    monkeypatch.undo()
    # the same file edited in place: named, and said to differ from what was tiled
    edited = fractal((60, 60), 13)
    import rasterio

    with rasterio.open(a, "r+") as ds:
        ds.write(edited.astype(ds.dtypes[0]), 1)
    with pytest.raises(
        JobMismatchError,
        match=r"source: '.*a\.tif' is not the file the store was tiled from as it was then",
    ):
        tile(a, tmp_path / "t.zarr", opts)


def test_killed_during_layout_is_recreated(dem_factory, tmp_path):
    from dataclasses import replace

    import tiler.destination as dest

    src = dem_factory(fractal((40, 40), 13))
    tile(src, tmp_path / "ref.zarr", TileOptions(block_size=17))
    meta = open_store(tmp_path / "ref.zarr").meta
    meta = replace(meta, complete=False, extra=dict(meta.extra, state="layout"))
    dest.fresh_group(Location(tmp_path / "s.zarr"), meta)  # the kill: root written only
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def test_second_writer_refused_and_stale_lease_taken_over(dem_factory, tmp_path, caplog):
    src = dem_factory(fractal((40, 40), 14))
    loc = Location(tmp_path / "s.zarr")
    other = WriterLease(loc, timeout_s=30).acquire()  # another live writer
    try:
        with pytest.raises(StoreLockedError, match=r"being written by process \d+ on host"):
            tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    finally:
        other.stop()  # a dead writer: its lease stays, its heartbeat stops
    rec = json.loads(loc.get_bytes(LEASE_KEY))
    rec["heartbeat"] = time.time() - 100
    loc.put_bytes(LEASE_KEY, json.dumps(rec).encode())
    with caplog.at_level(logging.WARNING):
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, lease_timeout_s=30))
    assert "taking over the stale writer lease" in caplog.text
    assert not loc.key_exists(LEASE_KEY)


def test_lease_being_created_is_not_taken_over(tmp_path):
    """A lease record that is empty for an instant (another writer creating it) is not stale:
    the second writer waits for it to become readable and is then refused."""
    loc = Location(tmp_path / "s.zarr")
    os.makedirs(tmp_path / "s.zarr")
    (tmp_path / "s.zarr" / LEASE_KEY).write_bytes(b"")  # created, not yet written
    other = WriterLease(loc, timeout_s=30)
    timer = threading.Timer(0.3, lambda: loc.put_bytes(LEASE_KEY, other._payload()))
    timer.start()
    try:
        with pytest.raises(StoreLockedError, match=r"being written by process \d+ on host"):
            WriterLease(loc, timeout_s=30).acquire()
    finally:
        timer.join()
    assert json.loads(loc.get_bytes(LEASE_KEY))["token"] == other.record["token"]


def test_lease_unreadable_for_the_grace_period_is_taken_over(tmp_path, caplog):
    """Positive control for the test above: a record that stays garbage is a dead writer's."""
    loc = Location(tmp_path / "s.zarr")
    os.makedirs(tmp_path / "s.zarr")
    (tmp_path / "s.zarr" / LEASE_KEY).write_bytes(b'{"host": "x", "pi')
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING):
        lease = WriterLease(loc, timeout_s=30).acquire()
    try:
        assert time.monotonic() - t0 >= UNREADABLE_GRACE_S
        assert "unreadable" in caplog.text
        assert json.loads(loc.get_bytes(LEASE_KEY))["token"] == lease.record["token"]
    finally:
        lease.release()
    assert not loc.key_exists(LEASE_KEY)


def test_put_if_absent_never_shows_partial_content(tmp_path):
    """Local put_if_absent makes the file appear whole (a reader polling it never sees b"")."""
    loc = Location(tmp_path / "x")
    payload = b"y" * (1 << 22)
    seen: list[int] = []
    stop = threading.Event()

    def poll():
        path = tmp_path / "x" / "k"
        while not stop.is_set():
            with contextlib.suppress(FileNotFoundError):
                seen.append(len(path.read_bytes()))

    t = threading.Thread(target=poll, name="test-poll")
    t.start()
    try:
        assert loc.put_if_absent("k", payload)
        time.sleep(0.05)
    finally:
        stop.set()
        t.join(timeout=10)
    assert seen and set(seen) == {len(payload)}
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == ["k"]  # no temporary left


def test_overwrite_under_open_reader(dem_factory, tmp_path):
    a = dem_factory(fractal((40, 40), 15), "a.tif")
    b = dem_factory(fractal((40, 40), 16), "b.tif")
    tile(a, tmp_path / "s.zarr", TileOptions(block_size=17))
    reader = open_store(tmp_path / "s.zarr")
    before = reader.read_block((0, 0))
    tile(b, tmp_path / "s.zarr", TileOptions(block_size=17, overwrite=True))
    with pytest.raises(StoreChangedError, match="replaced or rewritten"):
        reader.read_block((0, 0))
    assert not np.array_equal(open_store(tmp_path / "s.zarr").read_block((0, 0)), before)
    assert not list(tmp_path.glob("s.zarr.*"))  # no temporary or old directory left


def test_overwrite_refuses_while_another_writer_holds_the_lease(dem_factory, tmp_path):
    src = dem_factory(fractal((40, 40), 17))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    other = WriterLease(Location(tmp_path / "s.zarr"), timeout_s=30).acquire()
    try:
        with pytest.raises(StoreLockedError):
            tile(src, tmp_path / "s.zarr", TileOptions(block_size=17, overwrite=True))
        assert open_store(tmp_path / "s.zarr").meta.complete  # untouched
    finally:
        other.release()


def test_finished_store_needs_overwrite(dem_factory, tmp_path):
    src = dem_factory(fractal((30, 30), 18))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    with pytest.raises(StoreExistsError, match="overwrite"):
        tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))


def test_tile_from_a_plain_script_without_main_guard(dem_factory, tmp_path):
    src = dem_factory(fractal((120, 120), 19))
    script = tmp_path / "plain.py"
    script.write_text(
        textwrap.dedent(
            f"""
            import logging
            logging.basicConfig(level=logging.INFO)
            from tiler.tile import TileOptions, tile
            s = tile({str(src)!r}, {str(tmp_path / "s.zarr")!r},
                     TileOptions(block_size=17, workers=2, executor="processes"))
            print("blocks", s.tile_summary.blocks_computed, s.tile_summary.executor)
            """
        )
    )
    import os

    env = dict(os.environ, PYTHONPATH=os.getcwd())
    r = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env
    )
    assert r.returncode == 0, r.stderr
    assert "blocks 64 threads" in r.stdout
    assert "no `if __name__ == '__main__':` guard" in r.stderr


def test_tile_from_a_script_on_standard_input(dem_factory, tmp_path):
    """``python - < script.py``: spawned workers cannot re-import '<stdin>' (every worker died,
    reported as "out of memory or killed"); threads are used instead, with the reason. The
    same text run as a guarded file uses processes (the control)."""
    src = dem_factory(fractal((120, 120), 19))
    import os

    def script(dst: str, guard: bool) -> str:
        body = (
            "import logging\n"
            "logging.basicConfig(level=logging.INFO)\n"
            "from tiler.tile import TileOptions, tile\n"
            f"s = tile({str(src)!r}, {dst!r}, TileOptions(block_size=17, workers=2, "
            'executor="processes"))\n'
            'print("blocks", s.tile_summary.blocks_computed, s.tile_summary.executor)\n'
        )
        if guard:
            body = "if __name__ == '__main__':\n" + textwrap.indent(body, "    ")
        return body

    env = dict(os.environ, PYTHONPATH=os.getcwd())
    r = subprocess.run(
        [sys.executable, "-"],
        input=script(str(tmp_path / "a.zarr"), False),
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    assert "blocks 64 threads" in r.stdout
    assert "'<stdin>' is not a file worker processes can import" in r.stderr
    guarded = tmp_path / "guarded.py"
    guarded.write_text(script(str(tmp_path / "b.zarr"), True))
    r = subprocess.run(
        [sys.executable, str(guarded)], capture_output=True, text=True, timeout=120, env=env
    )
    assert r.returncode == 0, r.stderr
    assert "blocks 64 processes" in r.stdout


def test_all_fill_index_chunks_are_written(dem_factory, tmp_path):
    # one exactly fitting block: has_nodata is all False (= the fill value) and must be stored
    s = tile(dem_factory(fractal((17, 17), 20)), tmp_path / "s.zarr", TileOptions(block_size=17))
    assert not s.index.has_nodata.any()
    assert (tmp_path / "s.zarr" / "index" / "has_nodata" / "c" / "0" / "0").is_file()
    assert verify_store(tmp_path / "s.zarr").ok


def test_verify_over_http_and_memory(dem_factory, tmp_path):
    from rangeserver import LoopbackServer

    src = dem_factory(fractal((40, 40), 21))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=17))
    tile(src, "memory://verify-test/s.zarr", TileOptions(block_size=17))
    assert verify_store("memory://verify-test/s.zarr", source=src).ok
    with LoopbackServer(tmp_path) as url:
        rep = verify_store(f"{url}/s.zarr")
        assert rep.ok and rep.chunks_checked > 20, rep.problems
        (tmp_path / "s.zarr" / "errors" / "c" / "1" / "1" / "0" / "0").unlink()
        rep = verify_store(f"{url}/s.zarr")
        assert rep.bad_blocks == {(1, 1)} and rep.problems[0].kind == "missing"


def test_killed_while_finishing_is_finished_by_a_rerun(dem_factory, tmp_path, monkeypatch):
    import tiler.assemble as assemble

    src = dem_factory(fractal((60, 60), 22))
    opts = TileOptions(block_size=17, executor="threads")
    tile(src, tmp_path / "ref.zarr", opts)

    def killed(group, meta, index=None):
        raise KeyboardInterrupt("killed after the journal was consumed")

    monkeypatch.setattr(assemble, "complete", killed)
    with pytest.raises(TilingInterrupted):
        tile(src, tmp_path / "s.zarr", opts)
    monkeypatch.undo()
    meta = json.loads((tmp_path / "s.zarr" / "zarr.json").read_text())["attributes"]
    assert meta["terrastream"]["state"] == "finishing"
    # and killed half-way through deleting the journal (a deleted chunk must not matter)
    arr = zarr.open_array(
        tmp_path / "s.zarr",
        path="journal",
        mode="w",
        shape=(4, 4, 8),
        chunks=(1, 1, 8),
        dtype="uint8",
        fill_value=0,
    )
    arr[0, 0] = np.ones(8, np.uint8)
    s = tile(src, tmp_path / "s.zarr", opts)
    assert s.tile_summary.blocks_computed == 0 and s.tile_summary.resumed
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def test_damaged_shard_index_marks_its_blocks_and_is_repaired(dem_factory, tmp_path):
    import shutil

    src = dem_factory(fractal((150, 150), 23))
    opts = TileOptions(block_size=65, executor="threads")
    tile(src, tmp_path / "ref.zarr", opts)
    shutil.copytree(tmp_path / "ref.zarr", tmp_path / "s.zarr")
    shard = tmp_path / "s.zarr" / "levels" / "2" / "c" / "0" / "0" / "0"
    data = bytearray(shard.read_bytes())
    data[-3] ^= 1  # inside the shard index (at the end of the shard)
    shard.write_bytes(bytes(data))
    rep = verify_store(tmp_path / "s.zarr")
    assert len(rep.bad_blocks) == 9 and rep.problems[0].kind == "checksum"
    tile(src, tmp_path / "s.zarr", replace_opts(opts, repair=True))
    assert diff_stores(tmp_path / "s.zarr", tmp_path / "ref.zarr") == []


def replace_opts(opts: TileOptions, **kw) -> TileOptions:
    from dataclasses import replace

    return replace(opts, **kw)


def test_overwrite_and_resume_on_memory_url(dem_factory, monkeypatch):
    a = dem_factory(fractal((60, 60), 24), "a.tif")
    b = dem_factory(fractal((60, 60), 25), "b.tif")
    url = "memory://ow-test/s.zarr"
    opts = TileOptions(block_size=17, executor="threads", workers=1)
    _interrupt(monkeypatch, 5)
    with pytest.raises(TilingInterrupted):
        tile(a, url, opts)
    monkeypatch.undo()
    s = tile(a, url, opts)
    assert s.tile_summary.blocks_skipped == 5
    s2 = tile(b, url, replace_opts(opts, overwrite=True))
    assert verify_store(url, source=b).ok and s2.meta.generation != s.meta.generation
    with pytest.raises(StoreChangedError):
        s.read_block((0, 0))
    assert not Location(url).key_exists(LEASE_KEY)


@pytest.fixture(params=["local", "memory", "http"])
def store_url(request, dem_factory, tmp_path):
    """The same small store reachable as a local path, a memory:// URL and over HTTP."""
    data = fractal((50, 50), 26)
    src = dem_factory(data)
    opts = TileOptions(block_size=17, executor="threads")
    if request.param == "memory":
        url = f"memory://fixture-{tmp_path.name}/s.zarr"
        tile(src, url, opts)
        yield url, data, src
        return
    tile(src, tmp_path / "s.zarr", opts)
    if request.param == "local":
        yield str(tmp_path / "s.zarr"), data, src
        return
    from rangeserver import LoopbackServer

    with LoopbackServer(tmp_path) as base:
        yield f"{base}/s.zarr", data, src


def test_every_backend_reads_verifies_and_checks_generation(store_url):
    url, data, src = store_url
    s = open_store(url)
    for b in s.grid.blocks():
        r0, c0, h, w = s.grid.block_window(*b)
        np.testing.assert_array_equal(s.read_block(b)[:h, :w], data[r0 : r0 + h, c0 : c0 + w])
    s.check_unchanged(force=True)  # quiet: nothing changed
    assert verify_store(url, source=src).ok
    assert s.nbytes()["total"] > 0 or url.startswith("http")  # HTTP cannot list


def test_a_file_is_not_a_store(dem_factory, tmp_path):
    """The DEM given where its store was meant raised NotADirectoryError on 'dem.tif/zarr.json'
    (the API: open_store, open_session, xarray's engine); a StoreError naming it now."""
    from streamer.session import open_session
    from tiler.store import open_store

    src = dem_factory(fractal((40, 40), 6))
    for opener in (open_store, open_session):
        with pytest.raises(StoreError, match="is a file, not a store"):
            opener(str(src))
    tile(src, tmp_path / "s.zarr", TileOptions(block_size=33))
    assert open_store(tmp_path / "s.zarr").meta.complete  # the control: the store opens
