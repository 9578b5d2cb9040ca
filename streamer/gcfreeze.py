"""Keep Python's full garbage collections out of the frames (no I/O, no threads).

A full (generation-2) collection walks every object the collector tracks. After the imports
(numba, zarr, numpy: ~150,000 objects) and a warm-up, one such pass took 76–96 ms on the 2-core
flight of ``bench/gc_freeze.py``, and it runs on whichever thread allocates when it triggers: a
pass on a loader or the planning thread holds the GIL the caller's ``update`` waits for, and
the frame stalls. :func:`freeze_heap`
collects once and then moves everything alive to the collector's permanent generation
(:func:`gc.freeze`), so later full passes walk only what was allocated since. The objects stay
alive as before (reference counting still frees them); only a reference cycle among them that
becomes garbage later is never reclaimed. Process-wide: an application that owns its process
calls it once its start-up is done (``SessionConfig(freeze_gc=True)`` does it at the end of
``Session.warm_up``; the ``stream`` and ``view`` commands do).
"""

from __future__ import annotations

import gc


def freeze_heap() -> int:
    """Collect every generation, then freeze what is left (:func:`gc.freeze`): the number of
    objects now outside the collector's passes."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def tracked_in_passes() -> int:
    """Objects a full collection would walk now (every generation, the frozen ones excluded)."""
    return sum(len(gc.get_objects(generation=g)) for g in range(3))
