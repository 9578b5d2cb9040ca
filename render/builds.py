"""Per-block CPU builds on a worker thread, so the render thread does not wait for them: at
most one pending build per block (the latest one asked for), results taken by the render
thread when it next looks (``geometry-splitting``'s quadtree textures on a level change).

No GL here: a build is a plain function of arrays gathered on the render thread; uploading
its result stays on the render thread."""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable, Hashable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from typing import Generic, TypeVar

from render.errors import RenderError

T = TypeVar("T")
THREAD_PREFIX = "terrastream-block-build"


class BuildError(RenderError):
    """A background build failed (raised on the render thread, the worker's error chained)."""


class BackgroundBuilds(Generic[T]):
    """Builds keyed by ``(key, version)`` on one named worker thread. :meth:`want` asks for
    one (a key's earlier pending build is cancelled if not started, and its result dropped if
    it was); :meth:`done` hands back the finished ones; a failed build raises there."""

    def __init__(self, what: str = "a block's data", name: str = "") -> None:
        self.what = what
        prefix = f"{THREAD_PREFIX}-{name}" if name else THREAD_PREFIX  # (the thread's name)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=prefix)
        self._pending: dict[Hashable, tuple[Hashable, Future[T], str]] = {}
        self._unfinished: set[Future[T]] = set()  # replaced ones too (close waits for them)
        self._lock = threading.Lock()  # (want/done run on one thread; close may not)
        self._closer = weakref.finalize(self, self._pool.shutdown, False, cancel_futures=True)

    def want(
        self, key: Hashable, version: Hashable, build: Callable[[], T], what: str = ""
    ) -> bool:
        """Build ``key`` at ``version`` unless that build is already pending; whether one was
        submitted (``what``: the build in an error message, default: the builds' own ``what``
        for ``key``)."""
        with self._lock:
            old = self._pending.get(key)
            if old is not None and old[0] == version:
                return False
            if old is not None:
                old[1].cancel()  # (a running one finishes; done() drops its stale result)
            label = what or f"building {self.what} for {key} (version {version})"
            fut = self._pool.submit(build)
            self._unfinished.add(fut)
            fut.add_done_callback(self._unfinished.discard)
            self._pending[key] = (version, fut, label)
            return True

    def pending(self, key: Hashable) -> Hashable | None:
        """The version of ``key``'s pending build, or None."""
        with self._lock:
            item = self._pending.get(key)
            return None if item is None else item[0]

    def __len__(self) -> int:
        return len(self._pending)

    def done(self) -> list[tuple[Hashable, Hashable, T]]:
        """The finished builds ``(key, version, result)``, each handed back once; a failed
        build raises :class:`BuildError` naming it (the other finished ones are handed back by
        the next call)."""
        with self._lock:
            finished = [(k, *item) for k, item in self._pending.items() if item[1].done()]
            for k, *_ in finished:
                del self._pending[k]
        done = [x for x in finished if not x[2].cancelled()]
        for i, (_, _, f, label) in enumerate(done):
            exc = f.exception()
            if exc is not None:
                with self._lock:  # (not lost: a later want of the same key replaces them)
                    for k, v, g, lab in done[:i] + done[i + 1 :]:
                        self._pending.setdefault(k, (v, g, lab))
                raise BuildError(f"{label} failed: {exc}") from exc
        return [(k, v, f.result()) for k, v, f, _ in done]

    def wait(self, timeout: float = 30.0) -> None:
        """Wait until every pending build has finished (``timeout`` s at most: then
        :class:`BuildError`)."""
        with self._lock:
            futures = [item[1] for item in self._pending.values()]
        _, left = wait_futures(futures, timeout=timeout)
        if left:
            raise BuildError(
                f"{len(left)} build(s) of {self.what} still running after {timeout:g} s"
            )

    def close(self, timeout: float = 10.0) -> None:
        """Cancel what has not started, wait for a running build (``timeout`` s at most) and
        stop the worker thread."""
        with self._lock:
            futures = list(self._unfinished)
            self._pending.clear()
        for f in futures:
            f.cancel()
        _, left = wait_futures(futures, timeout=timeout)
        self._closer.detach()
        # nothing left running: the worker sees the shutdown at once (a bounded join)
        self._pool.shutdown(wait=not left, cancel_futures=True)
        if left:
            raise BuildError(f"a build of {self.what} still ran {timeout:g} s after close()")
