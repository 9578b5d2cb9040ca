"""``render.strategies.geometry_splitting.ahead.AheadTextures``: which first textures
geometry-splitting builds ahead for blocks the session holds but does not draw yet, and what it
keeps of them (pure bookkeeping, no GL, no threads)."""

from __future__ import annotations

from render.strategies.geometry_splitting.ahead import AheadTextures


def _by_row(blocks):
    """'Nearest first' for the tests: the lowest row first."""
    return sorted(blocks)


def _capped(level: int) -> int:
    return min(level, 6)


def test_wants_the_nearest_blocks_not_drawn_at_their_first_level():
    a = AheadTextures(per_frame=2)
    held = {(3, 0): 9, (1, 0): 4, (2, 0): 10, (0, 0): 8}
    drawn = {(0, 0)}
    got = a.wanted(held, _capped, lambda b: b in drawn, _by_row)
    assert got == [((1, 0), 4), ((2, 0), 6)]  # (0, 0) drawn; levels capped; two a frame
    a.put((1, 0), 4, b"x" * 8, 6)
    a.put((2, 0), 6, b"y" * 16, 6)
    assert a.wanted(held, _capped, lambda b: b in drawn, _by_row) == [((3, 0), 6)]
    assert a.nbytes == 24


def test_a_finer_resident_level_wants_a_new_build_and_a_negative_level_none():
    a = AheadTextures()
    a.put((0, 0), 4, b"x" * 8, 6)
    assert a.wanted({(0, 0): 5}, _capped, lambda b: False, _by_row) == [((0, 0), 5)]
    assert a.wanted({(0, 0): 4}, _capped, lambda b: False, _by_row) == []
    assert a.wanted({(0, 0): 4}, lambda lv: -1, lambda b: False, _by_row) == []


def test_take_hands_over_a_texture_once_counting_hits_and_interims():
    a = AheadTextures()
    a.put((0, 0), 6, b"t" * 8, 6)
    assert a.take((0, 0), 6) == (6, b"t" * 8, 6)
    assert (a.hits, a.misses, a.interims, a.nbytes, a.ready) == (1, 0, 0, 0, {})
    assert a.take((0, 0), 6) is None  # handed over once
    a.put((1, 1), 4, b"u" * 8, 6)
    # built for another level (the session raised the block's): handed over as an interim,
    # with the level it was built for
    assert a.take((1, 1), 5) == (4, b"u" * 8, 6)
    assert (a.hits, a.misses, a.interims, a.nbytes, a.ready) == (1, 1, 1, 0, {})


def test_blocks_the_session_dropped_lose_their_textures_and_the_bytes_are_bounded():
    a = AheadTextures(limit_bytes=20, per_frame=10)
    a.put((0, 0), 6, b"a" * 8, 6)
    a.put((0, 1), 6, b"b" * 8, 6)
    held = {(0, 1): 6, (5, 5): 6}
    assert a.wanted(held, _capped, lambda b: False, _by_row) == [((5, 5), 6)]
    assert set(a.ready) == {(0, 1)} and a.dropped == 1 and a.nbytes == 8
    a.put((5, 5), 6, b"c" * 16, 6)  # 24 bytes kept: over the limit, nothing more wanted
    assert a.wanted({**held, (7, 7): 6}, _capped, lambda b: False, _by_row) == []
    a.put((5, 5), 6, b"c" * 8, 6)  # replaced, not added
    assert a.nbytes == 16
    assert a.wanted({**held, (7, 7): 6}, _capped, lambda b: False, _by_row) == [((7, 7), 6)]


def test_control_a_skipped_block_is_never_wanted():
    a = AheadTextures()
    held = {(0, 0): 6, (0, 1): 6}
    assert a.wanted(held, _capped, lambda b: False, _by_row) == [((0, 0), 6), ((0, 1), 6)]
    assert a.wanted(held, _capped, lambda b: b == (0, 0), _by_row) == [((0, 1), 6)]


def test_builds_asked_for_count_until_they_are_put():
    a = AheadTextures(per_frame=2)
    held = {(0, 0): 6, (0, 1): 6, (0, 2): 6}
    got = a.wanted(held, _capped, lambda b: False, _by_row)
    assert got == [((0, 0), 6), ((0, 1), 6)]
    for b, _ in got:
        a.asking(b)
    assert a.wanted(held, _capped, lambda b: False, _by_row) == []  # two asked: no room
    a.put((0, 0), 6, b"a" * 8, 6)
    assert a.asked == {(0, 1)}
    assert a.wanted(held, _capped, lambda b: False, _by_row) == [((0, 2), 6)]


def test_a_block_drawn_before_its_texture_was_taken_loses_it():
    a = AheadTextures()
    a.put((0, 0), 6, b"a" * 8, 6)
    assert a.wanted({(0, 0): 6}, _capped, lambda b: True, _by_row) == []
    assert a.ready == {} and a.nbytes == 0 and a.dropped == 1
