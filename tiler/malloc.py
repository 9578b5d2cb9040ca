"""glibc allocator settings for tiling worker processes (pure ctypes, no store, no thread).

Encoding a block allocates many temporaries of a few MiB (a 1025² block's float64 fields are
8.4 MiB each). glibc serves allocations above ``M_MMAP_THRESHOLD`` (128 KiB at start) with a
fresh ``mmap``, and returns freed heap above ``M_TRIM_THRESHOLD`` to the system; it normally
raises the mmap threshold as large blocks are freed, so a long-running worker reuses its heap.
Setting either variable explicitly switches that adjustment off, and dask's nanny does exactly
that: it starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536``
(``distributed.nanny.pre-spawn-environ``). Each temporary then costs zero-filled pages from the
kernel: measured on one 1025² int16 block (``bench/scale.py --malloc``), 8.5 k minor page faults
per block with the numba kernels and 66 k with the numpy ones, against 2.9 k and 7.6 k in a
plain process, and ~1.6x the CPU time with numpy.

:func:`tune_allocator` fixes both thresholds at values above one block's temporaries, so every
worker — our process pool's and a dask worker, whatever its environment — reuses its heap
(~0 faults per block after the first). It is called once per worker process by
``tiler.run.worker_setup`` and never in the caller's own process (the ``threads`` executor).
``TERRASTREAM_MALLOC_TUNE=0`` leaves the allocator alone. Not glibc (macOS, musl): a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

ENV = "TERRASTREAM_MALLOC_TUNE"
M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's own upper limit for the adjusted threshold (64-bit)
TRIM_THRESHOLD = 64 << 20  # keep up to this much free heap: a block's temporaries

_done = False


def tune_allocator() -> bool:
    """Fix glibc's mmap and trim thresholds for this process (see the module doc); True if
    they were set now or before, False where not applicable or disabled."""
    global _done
    if _done:
        return True
    if os.environ.get(ENV, "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
    ok = mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1 and ok
    _done = ok
    return ok
