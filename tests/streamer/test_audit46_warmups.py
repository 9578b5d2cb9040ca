"""Audit 46 (streaming): several warm-ups, and a warm-up between frames, lose no bytes.

A session's loads and discards split three ways (``streamer.run.frames_summary``): the
warm-ups', the frames' (real-time + prefetched, and ``discarded_bytes``) and those after the
last frame. Two faults broke the split:

* a second ``warm_up`` overwrote the first's figures, so ``warmup_bytes`` and
  ``warmup_discarded_bytes`` were the last warm-up's and ``frames_summary`` put the earlier
  one's share "after the frames". The warm-up figures now sum every warm-up's (``warmups``
  counts them; ``warmup_ms`` is their total);
* a warm-up after frames zeroed the real-time and prefetched bytes (and the I/O time) the
  loaders counted since the previous frame: they were in no figure. They stay the next frame's
  now, as that warm-up's discards already did; what arrives during it is the warm-up's alone.

Everything runs inline (``workers=0``): nothing arrives after the last frame unless a test
makes it, so the warm-ups' plus the frames' figures are the session's. A read hook adds up
the level bytes really read; a level is discarded as in ``test_audit46_discarded_frames.py``
(the block's level below evicted while it is decoded). Positive controls: before the fix the
two-warm-ups flight had ``loaded_after_frames_bytes`` (and ``discarded_after_frames_bytes``)
equal to the first warm-up's, and the warm-up-between-frames flight's frames and warm-ups
added up to less than the session's loads.
"""

from __future__ import annotations

from dataclasses import asdict

import pytest
from demtools import fractal, write_dem

from cli.formatters import format_summary
from streamer.frames import Totals
from streamer.paths import default_flythrough
from streamer.run import frames_summary, run_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 8 x 10 blocks of 33 samples (k = 5), 10 m cells."""
    tmp = tmp_path_factory.mktemp("warmups")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def _cams(store, n):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=600.0, viewport=(320, 240))


class _Reads:
    """A read hook adding up the level bytes read and keeping the latest level read."""

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
    the next decode of a level >= 1 (inline: the latest level read): it is discarded on
    arrival. ``hits`` lists the ``(block, level)`` so discarded."""

    def __init__(self, s, reads: _Reads) -> None:
        self.s, self.reads = s, reads
        self.decode = s.store.decode_next
        self.armed = False
        self.hits: list[tuple] = []

    def __call__(self, levels, raw):
        b, lv = self.reads.last
        if self.armed and lv >= 1:
            with self.s.loader.cv:
                assert self.s.cache.level(b) == lv - 1
                self.s.cache.drop_level(b)
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


def _lack(s, b, lv) -> None:
    """Evict ``b``'s levels from ``lv`` up."""
    with s.loader.cv:
        while s.cache.level(b) >= lv:
            s.cache.drop_level(b)


def _resident_target(frame):
    """A block of ``frame`` holding its needed level ``lv >= 1``, and ``lv``."""
    return next((b, lv) for b, (have, lv) in sorted(frame.blocks.items()) if 1 <= lv <= have)


def _split_holds(summary, rows, reads) -> dict:
    """The three-way split of the session's loads and discards, checked; the cut summary."""
    loaded_frames = sum(r["realtime_bytes"] + r["prefetched_bytes"] for r in rows)
    discarded_frames = sum(r["discarded_bytes"] for r in rows)
    cut = frames_summary(summary, rows)
    assert cut["loaded_bytes"] == summary["warmup_bytes"] + loaded_frames
    assert cut["discarded_bytes"] == summary["warmup_discarded_bytes"] + discarded_frames
    assert cut["loaded_bytes"] + cut["loaded_after_frames_bytes"] == summary["loaded_bytes"]
    assert (
        cut["discarded_bytes"] + cut["discarded_after_frames_bytes"] == summary["discarded_bytes"]
    )
    assert summary["loaded_bytes"] + summary["discarded_bytes"] == reads.nbytes
    return cut


# -- the quiet case: one warm-up ---------------------------------------------------------


def test_one_warm_up_then_frames_splits_as_before(store, monkeypatch):
    """One warm-up: ``warmups`` is 1, its figures are what it returned, nothing is "after
    the frames", and the summary line still says "warm-up before frame 0"."""
    cams = _cams(store, 4)
    s, reads, evict = _open(store, monkeypatch)
    with s:
        w = s.warm_up(cams[0])
        rows = [asdict(s.update(cam, wait=True).stats) for cam in cams]
        summary = s.summary()
    assert summary["warmups"] == 1 and not evict.hits
    assert summary["warmup_bytes"] == w["bytes"] > 0 and summary["warmup_ms"] == w["ms"]
    cut = _split_holds(summary, rows, reads)
    assert cut["loaded_after_frames_bytes"] == 0 == cut["discarded_after_frames_bytes"]
    assert "warm-up before frame 0: " in format_summary(cut)


# -- two warm-ups --------------------------------------------------------------------------


def test_two_warm_ups_then_frames_count_both_warm_ups(store, monkeypatch):
    """Positive control: two warm-ups (each discarding one level) for two poses, then frames.
    Before the fix the figures were the second's, and ``frames_summary`` moved the first's
    loads and discards "after the frames" (non-zero here: nothing is read after them)."""
    cams = _cams(store, 90)
    s, reads, evict = _open(store, monkeypatch)
    with s:
        evict.armed = True
        w1 = s.warm_up(cams[-1])
        evict.armed = True
        w2 = s.warm_up(cams[0])
        assert len(evict.hits) == 2
        rows = [asdict(s.update(cam, wait=True).stats) for cam in cams[:4]]
        summary = s.summary()
    assert w1["bytes"] > 0 and w2["bytes"] > 0  # each loaded something of its own
    assert w1["discarded_bytes"] == s.level_bytes[evict.hits[0][1]] > 0
    assert w2["discarded_bytes"] == s.level_bytes[evict.hits[1][1]] > 0
    assert summary["warmups"] == 2
    assert summary["warmup_bytes"] == w1["bytes"] + w2["bytes"]
    assert summary["warmup_discarded_bytes"] == w1["discarded_bytes"] + w2["discarded_bytes"]
    assert summary["warmup_ms"] == pytest.approx(w1["ms"] + w2["ms"])
    assert [r["discarded_bytes"] for r in rows] == [0] * 4  # (the warm-ups' are their own)
    cut = _split_holds(summary, rows, reads)
    assert cut["loaded_after_frames_bytes"] == 0
    assert cut["discarded_after_frames_bytes"] == 0
    assert "2 warm-ups (summed): " in format_summary(cut)


# -- a warm-up between frames ----------------------------------------------------------------


def test_a_warm_up_between_frames_keeps_the_loads_since_the_previous_frame(store, monkeypatch):
    """Positive control: after frame 0 the loaders load a level (and discard one) before a
    warm-up for another pose begins. Those bytes are the next frame's, the warm-up's loads
    its own: no byte is lost (before the fix the level's bytes were in no figure) or counted
    twice."""
    cams = _cams(store, 90)
    s, reads, evict = _open(store, monkeypatch)
    with s:
        f0 = s.update(cams[0], 0, wait=True)
        b, lv = _resident_target(f0)
        _lack(s, b, lv)
        evict.armed = True
        with s.loader.cv:
            s.loader.push(b)
        s.loader.load_inline(None)  # lv discarded, lv - 1 reloaded (the loaders, between
        s.loader.load_inline(None)  # frames), then lv (a pass reads a (block, level) once)
        assert evict.hits == [(b, lv)] and s.cache.level(b) >= lv
        between = s.loader.frame_realtime + s.loader.frame_prefetched
        assert between >= s.level_bytes[lv] > 0
        w = s.warm_up(cams[-1])
        assert w["bytes"] > 0 and w["discarded_bytes"] == 0
        f1 = s.update(cams[0], 0)  # back where frame 0 was (it reads what the warm-up
        summary = s.summary()  # evicted, inline: its own loads beside those between)
    rows = [asdict(f0.stats), asdict(f1.stats)]
    assert f1.stats.realtime_bytes + f1.stats.prefetched_bytes >= between
    assert f1.stats.discarded_bytes == s.level_bytes[lv]
    assert summary["warmup_bytes"] == w["bytes"]
    cut = _split_holds(summary, rows, reads)
    assert cut["loaded_after_frames_bytes"] == 0 == cut["discarded_after_frames_bytes"]


def test_a_warm_up_between_frames_with_nothing_pending_changes_no_frame(store, monkeypatch):
    """The quiet case: nothing loaded between frame 0 and the warm-up; the warm-up's loads
    are its own and the split holds."""
    cams = _cams(store, 90)
    s, reads, _evict = _open(store, monkeypatch)
    with s:
        f0 = s.update(cams[0], 0, wait=True)
        w = s.warm_up(cams[-1])
        f1 = s.update(cams[0], 0)
        summary = s.summary()
    assert w["bytes"] > 0 and summary["warmups"] == 1
    _split_holds(summary, [asdict(f0.stats), asdict(f1.stats)], reads)


# -- run_flythrough and the totals ------------------------------------------------------------


def test_run_flythrough_after_an_earlier_warm_up_splits_its_figures(store, monkeypatch):
    """A session warmed up once by its caller and once more by ``run_flythrough``: the
    flight's summary holds both warm-ups and nothing "after the frames"."""
    cams = _cams(store, 90)
    s, reads, _evict = _open(store, monkeypatch)
    with s:
        s.warm_up(cams[-1])
        result = run_flythrough(s, cams[:3], realtime=False)
    summary = result.summary
    assert summary["warmups"] == 2
    assert summary["loaded_after_frames_bytes"] == 0
    assert summary["loaded_bytes"] + summary["discarded_bytes"] == reads.nbytes


def test_totals_add_warmup_sums_and_counts():
    t = Totals()
    assert t.warmups == 0
    t.add_warmup({"ms": 2.0, "bytes": 10.0, "discarded_bytes": 1.0})
    t.add_warmup({"ms": 3.0, "bytes": 5.0, "discarded_bytes": 0.0})
    assert t.warmup == {"ms": 5.0, "bytes": 15.0, "discarded_bytes": 1.0, "count": 2}
    assert t.warmups == 2
    assert Totals(warmup={"ms": 1.0, "bytes": 4}).warmups == 1  # a mapping without a count
