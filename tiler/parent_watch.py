"""Worker processes that end with their parent (Linux): a ``tile`` killed with SIGKILL left its
worker processes running for ever, reparented and blocked on their task pipe (~100 MB each).

:func:`die_with_parent` asks the kernel (``prctl(PR_SET_PDEATHSIG)``) to send the calling
process SIGKILL when the thread that started it ends, and exits at once if the parent is
already gone. Pure ctypes; elsewhere than on Linux, a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> bool:
    """Have this process killed when ``parent_pid`` (its parent, which started it from a thread
    that lives as long as the process pool) dies; True if the kernel took the request."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        ok = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
    if os.getppid() != parent_pid:  # the parent died before the request: no signal will come
        os._exit(1)
    return ok
