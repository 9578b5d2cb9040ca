"""Mosaics (audit 45): a refused resume and ``verify --source`` name the source that changed,
not only the mosaic's first file; no NotGeoreferencedWarning escapes from reader threads."""

from __future__ import annotations

import calendar
import dataclasses
import os
import re
import threading
import time
import warnings

import numpy as np
import pytest
import rasterio
import rasterio._io
from demtools import fractal, write_dem
from rasterio.env import Env
from rasterio.errors import NotGeoreferencedWarning

from tiler.errors import JobMismatchError
from tiler.location import Location
from tiler.meta import read_meta, write_meta
from tiler.mosaic import MosaicReader, plan_mosaic
from tiler.resume import SOURCE_PARTS, check_same_job
from tiler.tile import TileOptions, tile
from tiler.verify import verify_store

CELL = 30.0
X0, Y0 = 500000.0, 5000000.0
OPTS = TileOptions(block_size=17, workers=1, executor="threads")
#: a modification time set on a file (``touch``)
STAMP = "2020-01-02 03:04:05 UTC"


def _pair(tmp_path):
    """Two 40x40 tiles side by side on one grid (sharing their edge column): a.tif, b.tif."""
    data = fractal((40, 79), 21)
    a = write_dem(tmp_path / "a.tif", np.ascontiguousarray(data[:, :40]), origin=(X0, Y0))
    b = write_dem(tmp_path / "b.tif", np.ascontiguousarray(data[:, 39:]),
                  origin=(X0 + 39 * CELL, Y0))  # fmt: skip
    return a, b


def _interrupted(monkeypatch, srcs, dst, n=3):
    """Tile ``srcs`` into ``dst`` until ``n`` blocks are done, then a Ctrl-C: unfinished."""
    import tiler.tile as tile_mod

    real = tile_mod.process_block
    count = {"n": 0}

    def flaky(window, params):
        count["n"] += 1
        if count["n"] > n:
            raise KeyboardInterrupt("simulated Ctrl-C")
        return real(window, params)

    monkeypatch.setattr(tile_mod, "process_block", flaky)
    with pytest.raises(KeyboardInterrupt):
        tile([str(p) for p in srcs], dst, OPTS)
    monkeypatch.setattr(tile_mod, "process_block", real)


def _edit_in_place(path):
    """Change some samples of ``path`` (same size, same header)."""
    with rasterio.open(path, "r+") as ds:
        data = ds.read(1)
        data[10:30, 10:30] += 7
        ds.write(data, 1)


def _rewrite_compressed(path):
    """Write ``path`` again with the same samples and header, deflated (another size)."""
    with rasterio.open(path) as ds:
        data, profile = ds.read(1), ds.profile
    with rasterio.open(path, "w", **dict(profile, compress="deflate")) as ds:
        ds.write(data, 1)


def _stamp(path):
    t = calendar.timegm(time.strptime(STAMP, "%Y-%m-%d %H:%M:%S UTC"))
    os.utime(path, (t, t))


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (_edit_in_place, r"its samples differ\)"),
        (_rewrite_compressed, r"its size \(\d+ bytes then, \d+ now\) differs"),
    ],
    ids=["edited-in-place", "rewritten-another-size"],
)
def test_a_refused_mosaic_resume_names_the_second_source_that_changed(
    tmp_path, monkeypatch, change, said
):
    """The refusal said "source: 'a.tif + 1 more' is not the file the store was tiled from"
    when b.tif changed (the job held one fingerprint for the mosaic): it now names b.tif, its
    place in the list and what differs."""
    a, b = _pair(tmp_path)
    _interrupted(monkeypatch, [a, b], tmp_path / "s.zarr")
    change(b)
    with pytest.raises(JobMismatchError) as info:
        tile([str(a), str(b)], tmp_path / "s.zarr", OPTS)
    msg = str(info.value)
    assert "source: 'b.tif' (source 2 of 2) is not the file the store was tiled from" in msg, msg
    assert re.search(said, msg), msg
    assert "'a.tif'" not in msg and "a.tif + 1 more" not in msg, msg  # (a.tif did not change)
    assert "--overwrite" in msg or "overwrite=True" in msg, msg  # (what to do)


def test_an_unchanged_or_only_touched_mosaic_still_resumes(tmp_path, monkeypatch):
    """The control: the sources as they were resume, a modification time alone (``touch``)
    not being compared; the resumed store verifies against both sources."""
    a, b = _pair(tmp_path)
    _interrupted(monkeypatch, [a, b], tmp_path / "s.zarr")
    _stamp(b)  # (touched: same bytes)
    store = tile([str(a), str(b)], tmp_path / "s.zarr", OPTS)
    assert store.tile_summary.resumed
    rep = verify_store(store.location, source=[str(a), str(b)])
    assert rep.ok and rep.source_checked, rep.problems


def test_a_store_begun_without_source_parts_resumes_and_keeps_the_old_message(
    tmp_path, monkeypatch
):
    """A store begun by the previous version (its job has one fingerprint, no per-source
    parts) still resumes, and a changed source is refused with the message of then."""
    a, b = _pair(tmp_path)
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, [a, b], dst)
    group = Location(dst).open_group("r+")
    meta = read_meta(group)
    job = dict(meta.extra["job"])
    assert SOURCE_PARTS in job  # (what this version writes)
    del job[SOURCE_PARTS]
    write_meta(group, dataclasses.replace(meta, extra={**meta.extra, "job": job}))
    with rasterio.open(b) as ds:
        original = ds.read(1)
    _edit_in_place(b)
    with pytest.raises(JobMismatchError, match=r"source: 'a\.tif \+ 1 more' is not the file"):
        tile([str(a), str(b)], dst, OPTS)
    with rasterio.open(b, "r+") as ds:  # put back as it was
        ds.write(original, 1)
    store = tile([str(a), str(b)], dst, OPTS)
    assert store.tile_summary.resumed
    assert verify_store(store.location, source=[str(a), str(b)]).ok


@pytest.mark.parametrize(
    ("old", "new", "said"),
    [
        (["a.tif", "b.tif"], ["a.tif", "c.tif"],
         "source 2 of 2: store was tiled from 'b.tif', this run reads 'c.tif'"),
        (["a.tif", "b.tif"], ["a.tif", "b.tif", "c.tif"],
         "sources: store was tiled from 2 ('a.tif', 'b.tif'), this run reads 3 ('a.tif', "
         "'b.tif', 'c.tif')"),
    ],
    ids=["another-second-file", "one-more-file"],
)  # fmt: skip
def test_a_mosaic_of_other_files_names_them(old, new, said):
    """Another file in the list, or one more: the label ("a.tif + 1 more") was the same."""

    def job(names, fp):
        files = [{"name": n, "size": 10, "mtime": None, "header": "h", "samples": None}
                 for n in names]  # fmt: skip
        return {"source_fingerprint": fp, SOURCE_PARTS: {"grid": "g", "files": files}}

    with pytest.raises(JobMismatchError) as info:
        check_same_job("s.zarr", job(old, "1"), job(new, "2"), sources=("a.tif + 1 more",) * 2)
    assert said in str(info.value), str(info.value)
    check_same_job("s.zarr", job(old, "1"), {**job(new, "1")})  # same fingerprint: resumes


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (_edit_in_place, r"its samples come from 'b\.tif'"),
        (_rewrite_compressed, None),  # (same samples: no block differs)
    ],
    ids=["edited-in-place", "rewritten-another-size"],
)
def test_verify_source_of_a_mosaic_names_the_source_a_bad_block_comes_from(tmp_path, change, said):
    """``verify --source a.tif b.tif`` said "block (r, c) differs from the source '.../a.tif
    + 1 more'" when b.tif had changed: each block now names the sources it comes from."""
    a, b = _pair(tmp_path)
    store = tile([str(a), str(b)], tmp_path / "s.zarr", OPTS)
    assert verify_store(store.location, source=[str(a), str(b)]).ok  # the control
    change(b)
    rep = verify_store(store.location, source=[str(a), str(b)])
    if said is None:
        assert rep.ok, rep.problems
        return
    assert rep.bad_blocks and all(p.kind == "source" for p in rep.problems), rep.problems
    for p in rep.problems:
        assert re.search(said, p.message), p.message


def test_verify_source_says_what_changed_in_a_source_a_bad_block_comes_from(tmp_path):
    """With another size and other samples, a bad block's message says the source's size
    differs from the tiling's (the job's per-source parts)."""
    a, b = _pair(tmp_path)
    store = tile([str(a), str(b)], tmp_path / "s.zarr", OPTS)
    _edit_in_place(b)
    _rewrite_compressed(b)
    rep = verify_store(store.location, source=[str(a), str(b)])
    assert rep.bad_blocks, rep.problems
    for p in rep.problems:
        assert "'b.tif' (source 2 of 2), which the block's samples come from, is not the file" in (
            p.message
        ), p.message
        assert re.search(r"its size \(\d+ bytes then, \d+ now\) differs", p.message), p.message


# -- NotGeoreferencedWarning from reader threads (task 2) ---------------------------------------

DEG = 1 / 30


def _warped_pair(tmp_path):
    """Two geographic tiles side by side, planned onto a local projection (a small grid)."""
    w = write_dem(tmp_path / "w.tif", fractal((31, 31), seed=1), crs="EPSG:4326",
                  origin=(10.0, 46.0), cell=DEG)  # fmt: skip
    e = write_dem(tmp_path / "e.tif", fractal((31, 31), seed=2), crs="EPSG:4326",
                  origin=(11.0, 46.0), cell=DEG)  # fmt: skip
    return w, e, plan_mosaic([str(w), str(e)], dst_crs="auto", resolution=(5000.0, 5000.0))


@pytest.mark.parametrize("where", ["opening a source", "masking by a hull"])
def test_no_not_georeferenced_warning_escapes_when_two_reader_threads_meet(
    tmp_path, monkeypatch, where
):
    """rasterio's ``geometry_mask`` builds an in-memory raster without a geotransform and hides
    the NotGeoreferencedWarning that raises inside ``warnings.catch_warnings()``, as opening a
    source hides its own: that swaps the process-wide filters, so another reader thread
    leaving its own catch_warnings meanwhile put the old filters back and the warning was
    printed (``tile -q`` of a reprojected mosaic, about one run in two with threads).

    Made certain here: thread A stops inside its catch_warnings (``where``) until thread B is
    inside rasterio's, which waits (at most 0.5 s) for A to leave. Before the fix B's warning
    escaped every time; now B waits for A to finish first and nothing escapes."""
    _, _, spec = _warped_pair(tmp_path)
    window = (10, 14, 2, 2)  # (on the seam: both sources, hull masks)
    b_reader = MosaicReader(spec)
    b_reader.read_window(*window)  # (B's sources are open: B only masks)
    a_inside, b_inside = threading.Event(), threading.Event()
    b_thread = threading.get_ident()
    real_open = rasterio.open

    def slow_open(*args, **kw):  # A, in open_raster's catch_warnings
        if where == "opening a source" and threading.get_ident() != b_thread:
            a_inside.set()
            b_inside.wait(0.5)
        return real_open(*args, **kw)

    def env(*args, **kw):  # inside rasterio's catch_warnings of the in-memory raster
        if kw.get("GDAL_MEM_ENABLE_OPEN"):
            if threading.get_ident() == b_thread and not b_inside.is_set():
                mine = warnings.filters
                b_inside.set()
                t0 = time.monotonic()
                while warnings.filters is mine and time.monotonic() - t0 < 0.5:
                    time.sleep(0.001)  # (until another thread swaps the filters back)
            elif where == "masking by a hull" and not a_inside.is_set():
                a_inside.set()
                b_inside.wait(0.5)
        return Env(*args, **kw)

    monkeypatch.setattr(rasterio, "open", slow_open)
    monkeypatch.setattr(rasterio._io, "Env", env)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning)  # (affine's `*`)
        a = threading.Thread(target=lambda: MosaicReader(spec).read_window(*window))
        a.start()
        assert a_inside.wait(5)
        b_reader.read_window(*window)
        a.join(5)
    escaped = [str(w.message) for w in seen if issubclass(w.category, NotGeoreferencedWarning)]
    assert b_inside.is_set() and not escaped, escaped


def test_a_threaded_tiling_of_a_reprojected_mosaic_warns_nothing(tmp_path):
    """The quiet case: a reprojected mosaic tiled by four threads records no
    NotGeoreferencedWarning (and reads as before: every block done)."""
    w, e, _ = _warped_pair(tmp_path)
    opts = TileOptions(block_size=17, workers=4, executor="threads", dst_crs="auto",
                       resolution=5000.0)  # fmt: skip
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning)
        store = tile([str(w), str(e)], tmp_path / "s.zarr", opts)
    escaped = [str(x.message) for x in seen if issubclass(x.category, NotGeoreferencedWarning)]
    assert not escaped, escaped
    assert store.index.exists.any()


# -- the journal on resume (task 3) -------------------------------------------------------------


@pytest.mark.parametrize("damaged", [False, True], ids=["intact", "one-entry-damaged"])
def test_a_resume_with_a_damaged_journal_entry_computes_that_block_again(
    tmp_path, monkeypatch, damaged
):
    """``done_blocks`` counts a journal entry whose crc32c fails as not done, but the check of
    the done blocks' source samples then read the whole journal at once and the resume failed
    with zarr's "Stored and computed checksum do not match". The block is now computed again
    and the store is the uninterrupted run's, byte for byte (the control: an intact journal)."""
    from storetools import diff_stores

    a, b = _pair(tmp_path)
    ref = tile([str(a), str(b)], tmp_path / "ref.zarr", OPTS).location.path
    dst = tmp_path / "s.zarr"
    _interrupted(monkeypatch, [a, b], dst, n=4)
    if damaged:
        entry = sorted((dst / "journal").glob("c.*"))[1]
        raw = bytearray(entry.read_bytes())
        raw[len(raw) // 2] ^= 0xFF
        entry.write_bytes(bytes(raw))
    store = tile([str(a), str(b)], dst, OPTS)
    assert store.tile_summary.resumed
    assert store.tile_summary.blocks_skipped == (3 if damaged else 4)
    assert diff_stores(dst, ref) == []
