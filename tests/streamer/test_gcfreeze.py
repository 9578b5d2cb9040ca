"""``freeze_gc``: a warm-up that leaves the start-up's objects out of later full collections
(streamer.gcfreeze), with its control (no freeze: a full pass walks them all)."""

from __future__ import annotations

import gc
import weakref

import pytest
from demtools import fractal, write_dem

from streamer.gcfreeze import freeze_heap, tracked_in_passes
from streamer.paths import default_flythrough
from streamer.session import open_session
from tiler.tile import TileOptions, tile


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gcf")
    src = write_dem(tmp / "d.tif", fractal((129, 161), 5), cell=10.0)
    return tile(src, tmp / "s.zarr", TileOptions(block_size=33, workers=1))


def _cams(store, n=20):
    z0, z1 = store.meta.extra["value_range"]
    return default_flythrough(store.grid, z0, z1, n, 60.0, viewport=(160, 120))


@pytest.mark.parametrize("freeze", [True, False])
def test_warm_up_with_freeze_gc_leaves_the_start_up_out_of_full_collections(store, freeze):
    assert gc.get_freeze_count() == 0  # (the autouse fixture unfroze any earlier test's)
    gc.collect()  # (earlier tests' garbage: what is alive now is what a freeze would keep)
    before = tracked_in_passes()
    assert before > 10_000  # the imports alone: what a full pass walks without a freeze
    cams = _cams(store)
    with open_session(store, budget_mb=16, workers=2, freeze_gc=freeze) as s:
        s.warm_up(cams[0])
        frozen, walked = gc.get_freeze_count(), tracked_in_passes()
        for cam in cams:  # the flight goes on as before
            assert s.update(cam, 1 / 60).blocks
    if freeze:
        assert frozen >= 0.9 * before
        assert walked < 0.05 * before  # a later full collection walks a few objects
    else:  # the control: nothing frozen, a full pass still walks everything
        assert frozen == 0 and walked >= 0.9 * before


def test_freeze_heap_collects_cycles_first_and_objects_stay_alive():
    class Node:
        pass

    a, b = Node(), Node()
    a.other, b.other = b, a  # a cycle that is garbage once the names go
    ref = weakref.ref(a)
    del a, b
    kept = {"alive": [1, 2, 3]}
    n = freeze_heap()
    assert n == gc.get_freeze_count() > 0
    assert ref() is None  # collected before the freeze, not kept for ever
    assert kept["alive"] == [1, 2, 3]
    gc.unfreeze()
    assert gc.get_freeze_count() == 0
