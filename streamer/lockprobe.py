"""An instrumented lock for checking a session's lock discipline (tests and benchmarks).

:func:`install` swaps a fresh :class:`Session`'s lock (the loader's condition, which
``update()`` waits on) for a :class:`ProbeLock` that records every hold: the holder thread's
name, its wall and thread-CPU duration. :meth:`ProbeLock.held_here` tells a wrapped function
whether its own thread holds the lock, so reads and decodes done under it can be counted
(:meth:`ProbeLock.forbid`). Install before the first ``update``/``warm_up``.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any


class ProbeLock:
    """A non-reentrant lock (``threading.Lock``'s interface) that records its holds."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._owner: int | None = None
        self._t0 = self._c0 = 0.0
        #: ``(thread name, wall s, thread-CPU s)`` per hold, in release order
        self.holds: list[tuple[str, float, float]] = []
        #: ``(thread name, what)`` of forbidden calls made while holding the lock
        self.violations: list[tuple[str, str]] = []
        #: ``(thread name, what)`` of every call of a :meth:`forbid`-wrapped function
        self.calls: list[tuple[str, str]] = []
        #: ``(thread name, wall s)`` from asking for the lock to holding it, per hold, in
        #: acquisition order; 0 for a lock found free (taken without waiting)
        self.waits: list[tuple[str, float]] = []
        #: where the lock was taken, per hold (parallel to :attr:`holds`)
        self.sites: list[str] = []
        self._site = ""

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        """``threading.Lock.acquire``; starts the hold's clocks."""
        site = _site(sys._getframe(1))  # before the clocks start: not part of the hold
        waited = 0.0  # a free lock is taken at once: no clock (its wall time would count
        ok = self._lock.acquire(False)  # a GIL switch before the call as a wait)
        if not ok and blocking:
            w0 = time.perf_counter()
            ok = self._lock.acquire(True, timeout)
            waited = time.perf_counter() - w0
        if ok:
            self._owner = threading.get_ident()
            self._site = site
            self.waits.append((threading.current_thread().name, waited))
            self._t0, self._c0 = time.perf_counter(), time.thread_time()
        return ok

    def release(self) -> None:
        """``threading.Lock.release``; records the hold."""
        wall, cpu = time.perf_counter() - self._t0, time.thread_time() - self._c0
        self.holds.append((threading.current_thread().name, wall, cpu))
        self.sites.append(self._site)
        self._owner = None
        self._lock.release()

    __enter__ = acquire

    def __exit__(self, *exc: object) -> None:
        self.release()

    def locked(self) -> bool:
        """Whether some thread holds the lock."""
        return self._lock.locked()

    def _is_owned(self) -> bool:  # what threading.Condition asks
        return self._owner == threading.get_ident()

    def held_here(self) -> bool:
        """Whether the calling thread holds the lock."""
        return self._is_owned()

    def forbid(self, fn: Callable[..., Any], what: str) -> Callable[..., Any]:
        """``fn`` recording a violation each time it is called under the lock."""

        @functools.wraps(fn)
        def wrapped(*args: Any, **kwargs: Any) -> Any:
            name = threading.current_thread().name
            self.calls.append((name, what))
            if self.held_here():
                self.violations.append((name, what))
            return fn(*args, **kwargs)

        return wrapped

    def by_role(self) -> dict[str, list[tuple[float, float]]]:
        """Holds grouped by thread role: ``caller``, ``loader``, ``planner``, ``other``."""
        out: dict[str, list[tuple[float, float]]] = {}
        for name, wall, cpu in self.holds:
            out.setdefault(_role(name), []).append((wall, cpu))
        return out

    def waits_by_role(self) -> dict[str, list[float]]:
        """Seconds each acquisition waited for the lock, grouped by thread role."""
        out: dict[str, list[float]] = {}
        for name, wait in self.waits:
            out.setdefault(_role(name), []).append(wait)
        return out

    def by_site(self) -> dict[str, list[tuple[float, float]]]:
        """Holds grouped by where the lock was taken (``module.function:line``)."""
        out: dict[str, list[tuple[float, float]]] = {}
        for (_, wall, cpu), site in zip(self.holds, self.sites, strict=True):
            out.setdefault(site, []).append((wall, cpu))
        return out

    def clear(self) -> None:
        """Forget the holds and waits recorded so far (e.g. a warm-up's); the lock is taken
        meanwhile (unrecorded), so a release cannot record a hold between the lists."""
        with self._lock:
            self.holds.clear()
            self.sites.clear()
            self.waits.clear()


_SKIP = (threading.__file__, __file__)


def _role(name: str) -> str:
    """A thread's role by its name: ``caller``, ``loader``, ``planner`` or ``other``."""
    if name.startswith("terrastream-load"):
        return "loader"
    if name.startswith("terrastream-plan"):
        return "planner"
    return "caller" if name == "MainThread" else "other"


def _site(frame: Any) -> str:
    """``module.function:line`` of the first frame outside :mod:`threading` and this module."""
    while frame is not None and frame.f_code.co_filename in _SKIP:
        frame = frame.f_back
    if frame is None:
        return "?"
    mod = os.path.splitext(os.path.basename(frame.f_code.co_filename))[0]
    return f"{mod}.{frame.f_code.co_name}:{frame.f_lineno}"


def install(session: Any) -> ProbeLock:
    """Give ``session`` (not yet updated) a probed lock; reads and decodes of its store and
    its planner's work made under the lock become :attr:`ProbeLock.violations`. Returns the
    probe."""
    probe = ProbeLock()
    cv = threading.Condition(probe)  # type: ignore[arg-type]
    session.loader.cv = session._cv = cv
    store = session.store
    for name in ("read_level_raw", "read_errors", "read_mask", "decode_next", "to_heights"):
        setattr(store, name, probe.forbid(getattr(store, name), name))
    planner = session.planner
    for name in ("needed", "prefetch"):
        setattr(planner, name, probe.forbid(getattr(planner, name), f"planner.{name}"))
    return probe
