"""Audit 46 (fly-throughs): ``flythrough``'s summary splits loads and discards as ``stream``.

``render.flythrough.flythrough`` computed its own ``loaded_after_frames_mb`` and reported no
discarded bytes. Its figures are now ``streamer.run.frames_summary``'s: ``loaded_mb`` (the
frames', as ``frames.csv`` sums them), ``warmup_mb`` and ``loaded_after_frames_mb`` add up to
the session's loads, and ``discarded_mb``, ``warmup_discarded_mb`` and
``discarded_after_frames_mb`` to its discards (levels read but thrown away on arrival). The
keys it had keep their names and meaning.

The flight runs inline (``workers=0``): after frame 0 a resident level is evicted and its
re-read discarded on arrival (its level below evicted while it is decoded, as in
``tests/streamer/test_audit46_discarded_frames.py``); after the last frame the loaders load a
level. Positive control: before the fix the summary had no ``discarded_mb`` (a ``KeyError``).
"""

from __future__ import annotations

import pytest
from gltools import make_context, rough, tile_dem

import render.flythrough as fly
from streamer.run import make_path
from tiler.store import open_store

pytestmark = pytest.mark.gl
make_context()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 129 x 129 DEM in 4 x 4 blocks of 33 samples."""
    return str(tile_dem(tmp_path_factory.mktemp("fly46"), rough(129, 7), 33))


class _Hooks:
    """Installed on the flight's session (``open_session`` wrapped): a read hook adding up
    the level bytes read, and ``store.decode_next`` that, once armed, evicts the decoding
    block's level below (inline: the latest level read) so that level is discarded."""

    def __init__(self, monkeypatch) -> None:
        self.monkeypatch = monkeypatch
        self.s = None
        self.read = 0
        self.last = None
        self.armed = False
        self.hits: list[tuple] = []
        real = fly.open_session

        def opened(*a, **kw):
            self.s = real(*a, **kw)
            self.s._read_hook = self.on_read
            self.decode = self.s.store.decode_next
            monkeypatch.setattr(self.s.store, "decode_next", self.on_decode)
            return self.s

        monkeypatch.setattr(fly, "open_session", opened)

    def on_read(self, block, level) -> None:
        if level >= 0:
            self.read += self.s.level_bytes[level]
            self.last = (block, level)

    def on_decode(self, levels, raw):
        b, lv = self.last
        if self.armed and lv >= 1 and self.s.cache.level(b) == lv - 1:
            with self.s.loader.cv:
                self.s.cache.drop_level(b)
            self.armed = False
            self.hits.append((b, lv))
        return self.decode(levels, raw)

    def lack_one(self) -> tuple:
        """Evict the finest level (>= 1) of a resident block; that block and level."""
        s = self.s
        b, lv = next((b, lv) for b, lv in sorted(s.resident_levels().items()) if lv >= 1)
        with s.loader.cv:
            while s.cache.level(b) >= lv:
                s.cache.drop_level(b)
        return b, lv


def test_flythrough_summary_splits_loads_and_discards(store, tmp_path, monkeypatch):
    hooks = _Hooks(monkeypatch)
    captured = {}
    real_close = fly.close_for_verdict

    def close(session):
        unfinished, summary = real_close(session)
        captured.update(summary)
        return unfinished, summary

    monkeypatch.setattr(fly, "close_for_verdict", close)
    s = open_store(store)
    cams = make_path(s, "default", frames=4, viewport=(64, 48))
    after = {}

    def on_frame(row) -> None:
        if row.frame == 0:  # frame 1 re-reads the level: discarded on arrival
            hooks.lack_one()
            hooks.armed = True
        if row.frame == len(cams) - 1:  # the loaders load a level after the last frame
            b, lv = hooks.lack_one()
            before = hooks.s.summary()["loaded_bytes"]
            with hooks.s.loader.cv:
                hooks.s.loader.push(b)
            hooks.s.loader.load_inline(None)
            after["bytes"] = hooks.s.summary()["loaded_bytes"] - before

    rows, summary = fly.flythrough(
        s, cams, tmp_path / "f", patch_log2=2, workers=0, save_every=0, on_frame=on_frame
    )
    mb = 2**20
    assert len(hooks.hits) == 1 and after["bytes"] > 0
    thrown = hooks.s.level_bytes[hooks.hits[0][1]]
    # the discards: all in the frames (no warm-up, none after the last frame)
    assert summary["discarded_mb"] == pytest.approx(thrown / mb)
    assert summary["warmup_discarded_mb"] == 0.0 == summary["discarded_after_frames_mb"]
    assert captured["discarded_bytes"] == thrown
    # the loads: the frames' (as frames.csv), a warm-up's (none) and after the last frame
    assert summary["loaded_mb"] == pytest.approx(sum(r.loaded_mb for r in rows))
    assert summary["warmup_mb"] == 0.0
    assert summary["loaded_after_frames_mb"] == pytest.approx(after["bytes"] / mb)
    split = summary["loaded_mb"] + summary["warmup_mb"] + summary["loaded_after_frames_mb"]
    assert split == pytest.approx(captured["loaded_bytes"] / mb)
    assert captured["loaded_bytes"] + captured["discarded_bytes"] == hooks.read


def test_a_plain_flythrough_reports_no_discards(store, tmp_path, monkeypatch):
    """The quiet case: nothing evicted, nothing discarded; the loads split as before."""
    hooks = _Hooks(monkeypatch)
    s = open_store(store)
    cams = make_path(s, "default", frames=3, viewport=(64, 48))
    rows, summary = fly.flythrough(s, cams, tmp_path / "f", patch_log2=2, workers=0)
    assert not hooks.hits
    assert summary["discarded_mb"] == 0.0 == summary["discarded_after_frames_mb"]
    assert summary["loaded_mb"] == pytest.approx(sum(r.loaded_mb for r in rows))
    assert summary["loaded_mb"] > 0
    assert summary["loaded_after_frames_mb"] == 0.0 == summary["warmup_mb"]
