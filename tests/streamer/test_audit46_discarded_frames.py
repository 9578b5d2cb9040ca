"""Audit 46 (streaming): the bytes read but discarded on arrival, per frame and cut to a flight.

Session 45 counted the levels read from the store and thrown away on arrival (the block lost
the level below meanwhile, or moved on) in ``summary()["discarded_bytes"]``, session-wide only:

* no frame said when: ``FrameStats.discarded_bytes`` now counts them since the previous frame
  (the warm-up's apart, ``summary()["warmup_discarded_bytes"]``, never in frame 0 as well), so
  that the session's figure is the warm-up's plus the frames' plus those after the last frame;
* ``streamer.run.frames_summary`` cut ``loaded_bytes`` to the warm-up and the frames but left
  ``discarded_bytes`` session-wide: it is cut the same way now, the rest in
  ``discarded_after_frames_bytes`` (and ``stream``'s summary text says which);
* the ``workers=0`` per-frame allowance (``inline_bytes_per_frame``) counted loaded bytes only:
  a read discarded on arrival cost the same I/O yet spent none of it, so the pass read on.

Everything runs inline (``workers=0``) but the ``stream`` command's check. A level is discarded
as in ``test_audit45_discarded.py``: the block's level below is evicted while the level is
decoded (what a loader thread's eviction does). A read hook adds up the level bytes really
read. The positive controls are the discarding cases: before the fix ``FrameStats`` had no
``discarded_bytes`` (an ``AttributeError``), ``frames_summary`` gave no
``discarded_after_frames_bytes`` (a ``KeyError``), and the allowance pass read a second level.
"""

from __future__ import annotations

import json
from dataclasses import asdict

import pytest
from demtools import fractal, write_dem
from typer.testing import CliRunner

from cli.formatters import format_summary
from streamer.paths import default_flythrough
from streamer.run import frames_summary
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 8 x 10 blocks of 33 samples (k = 5), 10 m cells."""
    tmp = tmp_path_factory.mktemp("discarded_frames")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def _cams(store, n):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=600.0, viewport=(320, 240))


class _Reads:
    """A read hook adding up the level bytes read (errors reads, level -1, carry none) and
    keeping the latest level read (inline, the next decode is that level's)."""

    def __init__(self, level_bytes: list[int]) -> None:
        self.level_bytes = level_bytes
        self.nbytes = 0
        self.last = None

    def __call__(self, block, level) -> None:
        if level >= 0:
            self.nbytes += self.level_bytes[level]
            self.last = (block, level)


class _EvictOnDecode:
    """``store.decode_next`` that, once armed, evicts the decoding block's level below during
    the next decode of a level >= 1: that level is discarded on arrival. ``hits`` lists the
    ``(block, level)`` so discarded."""

    def __init__(self, s, reads: _Reads) -> None:
        self.s, self.reads = s, reads
        self.decode = s.store.decode_next
        self.armed = False
        self.hits: list[tuple] = []

    def __call__(self, levels, raw):
        b, lv = self.reads.last
        if self.armed and lv >= 1:
            with self.s.loader.cv:
                assert self.s.cache.level(b) == lv - 1  # lv is the block's next level
                self.s.cache.drop_level(b)  # evicted meanwhile
            self.armed = False
            self.hits.append((b, lv))
        return self.decode(levels, raw)


def _open(store, monkeypatch, **kw):
    s = open_session(store, budget_mb=64, workers=0, **kw)
    reads = _Reads(s.level_bytes)
    s._read_hook = reads
    evict = _EvictOnDecode(s, reads)
    monkeypatch.setattr(s.store, "decode_next", evict)
    return s, reads, evict


def _resident_target(frame, skip=()):
    """A block of ``frame`` holding its needed level ``lv >= 1`` (not in ``skip``), and
    ``lv``."""
    return next(
        (b, lv)
        for b, (have, lv) in sorted(frame.blocks.items())
        if 1 <= lv <= have and b not in skip
    )


def _lack(s, b, lv) -> None:
    """Evict ``b``'s levels from ``lv`` up (as the cache's eviction drops them)."""
    with s.loader.cv:
        while s.cache.level(b) >= lv:
            s.cache.drop_level(b)


def _bytes(s, hits) -> int:
    return sum(s.level_bytes[lv] for _, lv in hits)


# -- quiet: nothing thrown away ----------------------------------------------------------


def test_a_plain_flight_reports_no_discarded_bytes_in_any_frame(store, monkeypatch):
    s, reads, evict = _open(store, monkeypatch)
    with s:
        s.warm_up(_cams(store, 1)[0])
        rows = [asdict(s.update(cam, wait=True).stats) for cam in _cams(store, 6)]
        summary = s.summary()
    assert not evict.hits and summary["loaded_bytes"] == reads.nbytes > 0
    assert [r["discarded_bytes"] for r in rows] == [0] * 6
    assert summary["warmup_discarded_bytes"] == 0 and summary["discarded_bytes"] == 0
    cut = frames_summary(summary, rows)
    assert cut["discarded_bytes"] == 0 and cut["discarded_after_frames_bytes"] == 0


# -- the frame a level was discarded in says so -------------------------------------------


def test_the_frame_a_level_was_discarded_in_counts_its_bytes(store, monkeypatch):
    """Positive control: the discard is in the frame after it and in no other (a non-zero
    per-frame figure, where before there was no field at all)."""
    here = _cams(store, 1)[0]
    s, reads, evict = _open(store, monkeypatch)
    with s:
        f0 = s.update(here, 0, wait=True)
        b, lv = _resident_target(f0)
        _lack(s, b, lv)
        evict.armed = True
        f1 = s.update(here, 0)  # reads lv (discarded on arrival), then lv - 1 again
        f2 = s.update(here, 0)  # and lv (a pass reads a (block, level) once)
        summary = s.summary()
    assert evict.hits == [(b, lv)]
    assert f0.stats.discarded_bytes == 0
    assert f1.stats.discarded_bytes == s.level_bytes[lv] > 0
    assert f2.stats.discarded_bytes == 0  # reset by the frame that took it
    assert summary["discarded_bytes"] == s.level_bytes[lv] and summary["discarded_levels"] == 1
    assert f1.blocks[b][0] == lv - 1 and f2.blocks[b][0] >= lv  # reloaded
    # the frame's figures: what it read is what it loaded plus what it discarded
    assert summary["loaded_bytes"] + summary["discarded_bytes"] == reads.nbytes


# -- warm-up + frames + after the last frame = the session ---------------------------------


def test_warm_up_frames_and_after_the_last_frame_add_up_to_the_session(store, monkeypatch):
    """One level discarded in the warm-up, one in frame 1 and one after the last frame (the
    loaders reading on, as ``stream``'s flights do until the session closes): each is counted
    once, and ``frames_summary`` keeps the warm-up's and the frames'. Also the control of the
    warm-up's share: counted in frame 0 too, the figures would add up to more than the
    session's."""
    here = _cams(store, 1)[0]
    s, reads, evict = _open(store, monkeypatch)
    with s:
        evict.armed = True
        w = s.warm_up(here)
        assert len(evict.hits) == 1
        warm = _bytes(s, evict.hits)
        assert w["discarded_bytes"] == warm > 0
        frames = [s.update(here, 0, wait=True)]
        b, lv = _resident_target(frames[0])
        _lack(s, b, lv)
        evict.armed = True
        frames += [s.update(here, 0), s.update(here, 0)]
        assert evict.hits[1:] == [(b, lv)]
        # after the last frame: a level lacked again, read and discarded by the loader
        b2, lv2 = _resident_target(frames[-1], skip={b})
        _lack(s, b2, lv2)
        evict.armed = True
        with s.loader.cv:
            s.loader.push(b2)
        s.loader.load_inline(None)
        assert evict.hits[2:] == [(b2, lv2)]
        summary = s.summary()
    rows = [asdict(f.stats) for f in frames]
    assert [r["discarded_bytes"] for r in rows] == [0, s.level_bytes[lv], 0]
    assert summary["warmup_discarded_bytes"] == warm
    after = s.level_bytes[lv2]
    in_flight = warm + sum(r["discarded_bytes"] for r in rows)
    assert summary["discarded_bytes"] == in_flight + after == _bytes(s, evict.hits)
    assert summary["discarded_levels"] == 3
    assert summary["loaded_bytes"] + summary["discarded_bytes"] == reads.nbytes
    cut = frames_summary(summary, rows)
    assert cut["discarded_bytes"] == in_flight
    assert cut["discarded_after_frames_bytes"] == after > 0
    assert cut["discarded_levels"] == 3  # (the session's count, as documented)
    # the loaded bytes split the same way (what was reloaded after the discard is loaded)
    assert cut["loaded_bytes"] + cut["loaded_after_frames_bytes"] == summary["loaded_bytes"]


def test_stream_summary_text_says_where_the_discarded_bytes_were(store, monkeypatch):
    """``format_summary`` of a flight's summary (cut to the frames) names the part after the
    last frame; of a session's own summary it still says "in the session"."""
    summary = {
        "frames": 2, "stall_frames": 0, "io_errors": 0, "needed_bytes": 2**20,
        "used_bytes": 2**20, "realtime_bytes": 0, "realtime_bytes_after_first_frame": 0,
        "loaded_bytes": 2**20, "wasted_bytes": 0, "warmup_bytes": 0, "warmup_ms": 0.0,
        "peak_resident_bytes": 2**20, "budget_bytes": 2**21, "max_update_ms": 1.0,
        "max_update_cpu_ms": 1.0, "discarded_bytes": 3 * 2**20, "warmup_discarded_bytes": 2**20,
    }  # fmt: skip
    rows = [{"realtime_bytes": 0, "prefetched_bytes": 0, "discarded_bytes": 2**20}] * 2
    text = format_summary(frames_summary(summary, rows))
    assert "discarded on arrival 3.00 MiB (in the warm-up and the frames; 0.00 MiB" in text
    rows = rows[:1]  # one frame's discards came after the last frame
    text = format_summary(frames_summary(summary, rows))
    assert "discarded on arrival 2.00 MiB (in the warm-up and the frames; 1.00 MiB more" in text
    assert "discarded on arrival 3.00 MiB (in the session)" in format_summary(summary)


# -- workers=0: the allowance counts a discarded read ---------------------------------------


def test_the_inline_allowance_counts_a_read_discarded_on_arrival(store, monkeypatch):
    """With a one-byte allowance an update reads one level. A level discarded on arrival was
    read all the same: the pass ends there (it read on before the fix: the level below
    again, twice the allowed I/O)."""
    here = _cams(store, 1)[0]
    s, reads, evict = _open(store, monkeypatch, inline_bytes_per_frame=1)
    with s:
        f0 = s.update(here, 0, wait=True)
        b, lv = _resident_target(f0)
        _lack(s, b, lv)
        evict.armed = True
        before = reads.nbytes
        f1 = s.update(here, 0)
        assert evict.hits == [(b, lv)]
        assert reads.nbytes - before == s.level_bytes[lv]  # the discarded read only
        assert f1.stats.discarded_bytes == s.level_bytes[lv]
        assert f1.stats.realtime_bytes + f1.stats.prefetched_bytes == 0
        f2 = s.update(here, 0)  # the next frame goes on: lv - 1 back
        assert f2.blocks[b][0] == lv - 1 and f2.stats.discarded_bytes == 0


def test_the_inline_allowance_still_reads_one_loaded_level(store, monkeypatch):
    """The quiet case: nothing discarded, a one-byte allowance reads (and loads) one level."""
    here = _cams(store, 1)[0]
    s, reads, evict = _open(store, monkeypatch, inline_bytes_per_frame=1)
    with s:
        f0 = s.update(here, 0, wait=True)
        b, lv = _resident_target(f0)
        _lack(s, b, lv)
        before = reads.nbytes
        f1 = s.update(here, 0)
    assert not evict.hits
    assert reads.nbytes - before == s.level_bytes[lv] == f1.stats.realtime_bytes
    assert f1.blocks[b][0] == lv and f1.stats.discarded_bytes == 0


# -- the stream command ---------------------------------------------------------------------


def test_stream_json_rows_and_summary_carry_the_discarded_split(store, tmp_path):
    """``stream --json``: every row has ``discarded_bytes``; the summary's is the warm-up's
    plus the rows', the rest ``discarded_after_frames_bytes`` (threads: what is discarded
    depends on timing, the split does not)."""
    from cli.main import app

    out = tmp_path / "s.json"
    args = ["stream", store.url, "--frames", "30", "--size", "160x120", "--json", str(out)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "discarded on arrival" in r.output and "after the last frame" in r.output
    d = json.loads(out.read_text())
    rows, summary = d["frames"], d["summary"]
    assert all("discarded_bytes" in row for row in rows)
    in_flight = summary["warmup_discarded_bytes"] + sum(row["discarded_bytes"] for row in rows)
    assert summary["discarded_bytes"] == in_flight
    assert summary["discarded_after_frames_bytes"] >= 0


# -- the prefetch benchmark ------------------------------------------------------------------


def test_prefetch_bench_reports_discarded_bytes(store, monkeypatch):
    """``bench/prefetch*.py``: the run's metrics, its table row and its compact per-frame rows
    carry the discarded bytes (one level discarded in frame 1 of a short inline flight)."""
    from bench.prefetch import checks
    from bench.prefetch_fly import derive, fly
    from bench.prefetch_report import _compact_rows, table

    cams = [_cams(store, 1)[0]] * 4
    s, _reads, evict = _open(store, monkeypatch, account_hull=True)  # (as the bench's)
    with s:
        s.warm_up(cams[0])
        f0 = s.update(cams[0], 0, wait=True)
        b, lv = _resident_target(f0)
        evicted = []

        def on_second_frame(camera, dt=None, *, wait=False, _update=s.update):
            if len(evicted) == 1:  # before frame 1 of the flight: lv lacked, then discarded
                _lack(s, b, lv)
                evict.armed = True
            evicted.append(True)
            return _update(camera, dt, wait=wait)

        monkeypatch.setattr(s, "update", on_second_frame)
        out = fly(s, cams)
        summary = s.summary()
    assert evict.hits == [(b, lv)]
    m = derive(out["rows"], summary, cams, out)
    assert m["discarded_bytes"] == summary["discarded_bytes"] == s.level_bytes[lv] > 0
    assert m["frames_discarded_bytes"] == s.level_bytes[lv] and m["frames_with_discards"] == 1
    rec = {"name": "t", "in_target_scope": False, "metrics": m, "checks": checks(m)}
    head, _rule, row, *_ = table([rec]).splitlines()
    assert "discMB" in head.split()
    assert row.split()[head.split().index("discMB")] == f"{s.level_bytes[lv] / 2**20:.3f}"
    compact = _compact_rows(out["rows"])
    col = compact["columns"].index("discarded_bytes")
    assert [r[col] for r in compact["rows"]] == [0, s.level_bytes[lv], 0, 0]
