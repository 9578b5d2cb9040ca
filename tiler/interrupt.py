"""Ctrl-C during a block run (or while the store's layout is created), raised where the code
chooses.

A ``KeyboardInterrupt`` raised wherever the main thread happens to be can land inside the
bookkeeping of ``concurrent.futures`` or ``distributed`` while one of their locks is held (a
future's condition, an executor's shutdown lock, a process half started). The pool's manager
thread then waits on that lock for ever, and shutting the pool down, which the interrupted run
must do, hangs with its workers alive (``threading.Condition.__enter__`` is Python code: the
interrupt can be raised after the lock is taken and before the ``with`` body owns it). While a run
waits for its workers, :class:`DeferredInterrupt` turns SIGINT into a flag; the loop waits in
short slices (:func:`wait_first`) and raises ``KeyboardInterrupt`` itself between them, with no
lock held.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

#: the longest a Ctrl-C waits to be noticed while no block finishes
POLL_S = 0.2

#: the :class:`DeferredInterrupt` contexts the main thread is inside (innermost last)
_ACTIVE: list[DeferredInterrupt] = []


def defer_active() -> bool:
    """Flag the innermost :class:`DeferredInterrupt` the main thread is inside, as a Ctrl-C
    would (for a SIGTERM handled as one while SIGINT is ignored, so no SIGINT handler is
    installed); False when there is none."""
    if not _ACTIVE:
        return False
    _ACTIVE[-1].interrupted = True
    return True


class DeferredInterrupt:
    """Context manager: inside it, SIGINT sets :attr:`interrupted` instead of raising.

    Installed only in the main thread and only over Python's default handler: a handler the
    caller set (or SIGINT ignored) is left alone. On leaving, the previous handler is put back,
    and a Ctrl-C that arrived after the last :meth:`check` is raised then, so none is lost.
    """

    def __init__(self, *, raise_on_exit: bool = True) -> None:
        #: False: a Ctrl-C noticed by no :meth:`check` is left in :attr:`interrupted` on
        #: leaving, not raised (work that, once done, leaves nothing to interrupt)
        self.raise_on_exit = raise_on_exit
        self.interrupted = False
        self._old: Any = None

    @property
    def installed(self) -> bool:
        """True if SIGINT is deferred (main thread, default handler at entry)."""
        return self._old is not None

    def _handler(self, signum: int, frame: Any) -> None:
        # an attribute, not a threading.Event: the handler runs in the main thread wherever it
        # is (even inside this handler, for a second Ctrl-C) and must take no lock
        self.interrupted = True

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` if a Ctrl-C arrived."""
        if self.interrupted:
            raise KeyboardInterrupt

    def __enter__(self) -> DeferredInterrupt:
        main = threading.current_thread() is threading.main_thread()
        if main:
            _ACTIVE.append(self)
        if main and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None
        if self in _ACTIVE:
            _ACTIVE.remove(self)
        if exc_type is None and self.raise_on_exit:
            self.check()


def wait_first(
    wait: Callable[[set[Any], float], set[Any]],
    pending: set[Any],
    timeout_s: float,
    interrupt: DeferredInterrupt,
    poll_s: float = POLL_S,
) -> set[Any]:
    """The futures of ``pending`` that finished first (empty after ``timeout_s`` with none).

    ``wait(pending, timeout)`` returns the finished ones (``concurrent.futures.wait`` or
    ``distributed.wait`` with ``FIRST_COMPLETED``); it is called in slices of at most ``poll_s``
    and ``interrupt`` is checked before each, so a Ctrl-C is raised here within ``poll_s``.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        interrupt.check()
        left = deadline - time.monotonic()
        if left <= 0:
            return set()
        finished = wait(pending, min(poll_s, left))
        if finished:
            return finished
