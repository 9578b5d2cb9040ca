"""Audit 45 (streaming): the bytes of levels read from the store and thrown away are counted.

A level read while its block stopped holding the level below it (evicted during the decode,
or the block no longer wanted at all), a level read beyond a gap that will not be filled, and a
level whose decode raised were dropped on arrival: their bytes were read, yet counted neither
in ``loaded_bytes`` nor as real-time or prefetched, so the byte figures under-reported the I/O
done. ``summary()["discarded_bytes"]`` (and ``discarded_levels``) now count them: the bytes read
from the store are ``loaded_bytes + discarded_bytes`` (decoded level bytes, as every figure).

Everything runs inline (``workers=0``); a read hook adds up what was really read (every level
read is called through it), against which the figures are checked. The positive controls are
the discarding cases: before the fix the summary had no ``discarded_bytes`` (a ``KeyError``),
and a level dropped because its block was evicted during its decode kept its reservation
(``cache.reserved`` stayed above 0 once idle: the budget shrank for good).
"""

from __future__ import annotations

import pytest
from demtools import fractal, write_dem

from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 257 x 321 store of 8 x 10 blocks of 33 samples (k = 5), 10 m cells."""
    tmp = tmp_path_factory.mktemp("discarded")
    src = write_dem(tmp / "d.tif", fractal((257, 321), 4), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1, executor="threads"))


def _cams(store, n):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, speed=600.0, viewport=(320, 240))


class _Reads:
    """A read hook adding up the level bytes read (errors reads, level -1, carry none);
    ``also`` is called after counting (to act while a read is under way)."""

    def __init__(self, level_bytes: list[int]) -> None:
        self.level_bytes = level_bytes
        self.nbytes = 0
        self.also = None

    def __call__(self, block, level) -> None:
        if level >= 0:
            self.nbytes += self.level_bytes[level]
        if self.also is not None:
            self.also(block, level)


def _open(store, **kw):
    s = open_session(store, budget_mb=64, workers=0, **kw)
    reads = _Reads(s.level_bytes)
    s._read_hook = reads
    return s, reads


def _resident_target(frame):
    """A block of ``frame`` holding its needed level ``lv >= 1``, and ``lv``."""
    return next((b, lv) for b, (have, lv) in sorted(frame.blocks.items()) if 1 <= lv <= have)


def _lack(s, b, lv) -> None:
    """Evict ``b``'s levels from ``lv`` up (as the cache's eviction drops them)."""
    with s.loader.cv:
        while s.cache.level(b) >= lv:
            s.cache.drop_level(b)


def _check_totals(s, reads) -> dict:
    """The summary, with no read under way (inline: between updates): what was read is what
    was loaded plus what was discarded, and no reservation is left over."""
    out = s.summary()
    assert out["loaded_bytes"] + out["discarded_bytes"] == reads.nbytes
    ld = s.loader
    with ld.cv:
        assert not any(ld.fetching.values()) and not any(ld.raw.values()) and not ld.decoding
        assert s.cache.reserved == 0
    return out


# -- quiet: nothing thrown away ----------------------------------------------------------


def test_a_plain_flight_discards_nothing(store):
    s, reads = _open(store)
    with s:
        for cam in _cams(store, 6):
            s.update(cam, wait=True)
        out = _check_totals(s, reads)
    assert out["loaded_bytes"] > 0 and reads.nbytes == out["loaded_bytes"]
    assert out["discarded_bytes"] == 0 and out["discarded_levels"] == 0


# -- a level whose block lost the level below it while it was decoded ----------------------


def test_a_level_whose_lower_level_was_evicted_during_its_decode_is_discarded(store, monkeypatch):
    here = _cams(store, 2)[0]
    s, reads = _open(store, inline_bytes_per_frame=1)
    with s:
        f = s.update(here, 0, wait=True)
        b, lv = _resident_target(f)
        _lack(s, b, lv)
        before = s.summary()
        assert before["discarded_bytes"] == 0
        decode = s.store.decode_next
        evicted = []

        def evicting_decode(levels, raw):
            if not evicted:  # the first decode is b's level lv (the only level short)
                with s.loader.cv:
                    assert s.cache.level(b) == lv - 1
                    s.cache.drop_level(b)  # evicted meanwhile
                evicted.append(True)
            return decode(levels, raw)

        monkeypatch.setattr(s.store, "decode_next", evicting_decode)
        read_before = reads.nbytes
        s.update(here, 0)  # reads lv (discarded on arrival), then lv - 1 again
        assert evicted
        out = _check_totals(s, reads)
    assert out["discarded_bytes"] == s.level_bytes[lv] and out["discarded_levels"] == 1
    assert (
        out["loaded_bytes"] - before["loaded_bytes"]
        == reads.nbytes - read_before - (s.level_bytes[lv])
    )


# -- a level whose block is no longer wanted when it arrives ---------------------------------


def test_a_level_of_a_block_unwanted_while_it_was_read_is_discarded(store):
    here = _cams(store, 2)[0]
    s, reads = _open(store, inline_bytes_per_frame=1)
    with s:
        gone = []

        def move_off(block, level):
            if level == 0 and not gone:  # the first level read: the camera leaves the DEM
                with s.loader.cv:
                    s.cache.set_wants({}, s.level_bytes)
                    assert s.cache.want(block) == (-1, -1) and s.cache.level(block) == -1
                gone.append(block)

        reads.also = move_off
        s.update(here, 0)  # reads errors, then one level 0: thrown away on arrival
        assert gone
        out = _check_totals(s, reads)
    assert out["loaded_bytes"] == 0 and reads.nbytes == s.level_bytes[0]
    assert out["discarded_bytes"] == s.level_bytes[0] and out["discarded_levels"] == 1


# -- a level read beyond a gap that will not be filled ---------------------------------------


def test_a_level_read_beyond_a_gap_that_will_not_be_filled_is_discarded(store):
    here = _cams(store, 2)[0]
    s, reads = _open(store, inline_bytes_per_frame=1)
    with s:
        f = s.update(here, 0, wait=True)
        b, lv = _resident_target(f)
        _lack(s, b, lv)
        loaded = s.summary()["loaded_bytes"]
        moved = []

        def evict_and_move_off(block, level):
            if (block, level) == (b, lv) and not moved:
                with s.loader.cv:
                    s.cache.set_wants({}, s.level_bytes)  # the camera leaves the DEM
                    s.cache.drop_level(b)  # and lv - 1 is evicted: lv arrives beyond a gap
                moved.append(True)

        reads.also = evict_and_move_off
        s.update(here, 0)
        assert moved
        out = _check_totals(s, reads)
    assert out["loaded_bytes"] == loaded
    assert out["discarded_bytes"] == s.level_bytes[lv] and out["discarded_levels"] == 1


# -- a level whose decode raised (a bug: re-raised by the update) --------------------------


def test_a_level_whose_decode_raised_is_discarded(store, monkeypatch):
    here = _cams(store, 2)[0]
    s, reads = _open(store, inline_bytes_per_frame=1)
    with s:
        f = s.update(here, 0, wait=True)
        b, lv = _resident_target(f)
        _lack(s, b, lv)

        def failing_decode(levels, raw):
            raise RuntimeError("injected decode failure")

        monkeypatch.setattr(s.store, "decode_next", failing_decode)
        with pytest.raises(RuntimeError, match="injected decode failure"):
            s.update(here, 0)
        out = _check_totals(s, reads)
    assert out["discarded_bytes"] == s.level_bytes[lv] and out["discarded_levels"] == 1
