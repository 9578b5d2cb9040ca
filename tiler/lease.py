"""The writer lease: one process writes a store at a time; a crashed writer never blocks forever.

The lease is a small JSON object under the key ``lease.json`` of the store: owner host, pid, a
random token, and a heartbeat time a named thread refreshes every ``timeout / 4`` seconds. A
second writer finds a fresh lease and is refused (:class:`StoreLockedError`, naming the owner and
how long until the lease goes stale); a lease whose heartbeat is older than the timeout belongs
to a dead writer and is taken over (logged). A record that cannot be parsed may be one another
writer is creating this instant, so it is stale only once it stayed unreadable for
``UNREADABLE_GRACE_S``. The lease is removed when the writer stops.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
import uuid
from typing import Any

from tiler.errors import StoreLockedError
from tiler.location import Location

log = logging.getLogger(__name__)
LEASE_KEY = "lease.json"
DEFAULT_TIMEOUT_S = 60.0
UNREADABLE_GRACE_S = 2.0  # a lease record that stays unparsable this long is stale
MAX_ATTEMPTS = 200  # bounded: grace-period polls (40) plus a few take-over rounds


def read_lease(loc: Location) -> dict[str, Any] | None:
    """The lease record at ``loc`` (None if there is none or it is unreadable)."""
    raw = loc.get_bytes(LEASE_KEY)
    if raw is None:
        return None
    try:
        d = json.loads(raw)
    except ValueError:
        d = None
    if not isinstance(d, dict):
        return {"host": "?", "pid": -1, "token": "?", "heartbeat": 0.0, "unreadable": True}
    return d


def lease_is_fresh(d: dict[str, Any], timeout_s: float) -> bool:
    """True if the lease's heartbeat is younger than ``timeout_s``."""
    return time.time() - float(d.get("heartbeat", 0.0)) < timeout_s


def live_writer(loc: Location, timeout_s: float = DEFAULT_TIMEOUT_S) -> str | None:
    """Who holds a live lease on ``loc`` (a fresh heartbeat, its process not known gone), for
    messages; None if no writer does."""
    d = read_lease(loc)
    if d is None or d.get("unreadable") or not lease_is_fresh(d, timeout_s) or _owner_gone(d):
        return None
    return _describe(d)


def _describe(d: dict[str, Any]) -> str:
    if d.get("unreadable"):
        return "a writer whose lease record is unreadable"
    age = time.time() - float(d.get("heartbeat", 0.0))
    return f"process {d.get('pid')} on host {d.get('host')!r} (last heartbeat {age:.0f} s ago)"


def _owner_gone(d: dict[str, Any]) -> bool:
    """True if the lease's owner ran on this host and that process is gone (a crash)."""
    if d.get("host") != socket.gethostname():
        return False
    try:
        pid = int(d.get("pid", -1))
    except (TypeError, ValueError):
        return False
    if pid <= 0 or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


class WriterLease:
    """Exclusive writer lease on one store; use as a context manager (or acquire/release)."""

    def __init__(self, loc: Location, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        if not timeout_s > 0:
            raise ValueError(f"lease timeout must be > 0 seconds, got {timeout_s}")
        self.loc, self.timeout_s = loc, float(timeout_s)
        self.record = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "token": uuid.uuid4().hex,
            "heartbeat": time.time(),
        }
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def _payload(self) -> bytes:
        self.record["heartbeat"] = time.time()
        return json.dumps(self.record).encode()

    def acquire(self) -> WriterLease:
        """Take the lease (taking over a stale one) or raise StoreLockedError."""
        unreadable_since: float | None = None
        for _ in range(MAX_ATTEMPTS):
            if self.loc.put_if_absent(LEASE_KEY, self._payload()):
                break
            cur = read_lease(self.loc)
            if cur is None:
                continue  # released between our two calls: try again
            if cur.get("token") == self.record["token"]:
                break
            if cur.get("unreadable"):
                # Another writer may be creating it this instant (a store whose writes are not
                # atomic): only a record that stays unreadable for the grace period is stale.
                now = time.monotonic()
                unreadable_since = now if unreadable_since is None else unreadable_since
                if now - unreadable_since < UNREADABLE_GRACE_S:
                    time.sleep(0.05)
                    continue
                reason = f"its record stayed unreadable for {UNREADABLE_GRACE_S:.0f} s"
            elif lease_is_fresh(cur, self.timeout_s) and not _owner_gone(cur):
                left = self.timeout_s - (time.time() - float(cur.get("heartbeat", 0.0)))
                raise StoreLockedError(
                    f"{self.loc.url!r} is being written by {_describe(cur)}; wait for it to "
                    f"finish. If that process is dead, its lease goes stale {left:.0f} s after "
                    f"its last heartbeat (timeout {self.timeout_s:.0f} s) and is then taken over."
                )
            elif _owner_gone(cur):
                reason = "that process no longer exists on this host"
            else:
                reason = f"no heartbeat for more than {self.timeout_s:.0f} s"
            log.warning(
                "taking over the stale writer lease of %s on %s (%s)",
                _describe(cur),
                self.loc.url,
                reason,
            )
            # Delete only the stale record we judged: a newer writer's fresh lease stays.
            if read_lease(self.loc) == cur:
                self.loc.delete_key(LEASE_KEY)
            unreadable_since = None
        else:
            raise StoreLockedError(f"could not take the writer lease of {self.loc.url!r}")
        self._thread = threading.Thread(
            target=self._beat, name="terrastream-lease-heartbeat", daemon=True
        )
        self._thread.start()
        return self

    def _beat(self) -> None:
        period = self.timeout_s / 4
        while not self._stop.wait(period):
            try:
                cur = read_lease(self.loc)
                if cur is not None and cur.get("token") != self.record["token"]:
                    self.error = StoreLockedError(
                        f"the writer lease of {self.loc.url!r} was taken over by "
                        f"{_describe(cur)} while this process was writing"
                    )
                    return
                self.loc.put_bytes(LEASE_KEY, self._payload())
            except OSError as exc:  # a flaky store: retried at the next beat
                log.warning("lease heartbeat on %s failed: %s", self.loc.url, exc)

    def check(self) -> None:
        """Raise if the heartbeat thread found the lease taken over."""
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        """Stop the heartbeat thread (the lease record stays until :meth:`release`)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None

    def reassert(self) -> None:
        """Write this lease's record again (after the store's contents were cleared)."""
        self.loc.put_bytes(LEASE_KEY, self._payload())

    def release(self) -> None:
        """Stop the heartbeat and remove the lease (if it is still ours)."""
        self.stop()
        cur = read_lease(self.loc)
        if cur is not None and cur.get("token") == self.record["token"]:
            self.loc.delete_key(LEASE_KEY)

    def __enter__(self) -> WriterLease:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
