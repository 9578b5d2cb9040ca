"""Progress for long commands: a tqdm bar on a terminal, periodic log lines elsewhere.

Without a TTY (logs, CI, batch jobs) a line such as
``tiling: 42.0 % (108/256 blocks), 31.5 MiB/s, 12 s elapsed, ~17 s left`` is written to stderr
every :data:`INTERVAL_S` seconds (``TERRASTREAM_PROGRESS_S`` overrides it) and once at the end.
``-q`` silences both.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any, TextIO

from cli.common import state

INTERVAL_S = 5.0


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get("TERRASTREAM_PROGRESS_S", INTERVAL_S)))
    except ValueError:
        return INTERVAL_S


class Progress:
    """``update(done, total, rate=...)`` as often as wanted; ``close()`` once."""

    def __init__(
        self, desc: str, unit: str, *, stream: TextIO | None = None, quiet: bool | None = None
    ) -> None:
        self.desc, self.unit = desc, unit
        self.stream = stream or sys.stderr
        self.t0 = time.monotonic()
        self.last_line = -float("inf")
        self.done, self.total, self.note = 0, 0, ""
        self.lines = 0
        self.printed: tuple[int, int] | None = None
        self.quiet = state.quiet if quiet is None else quiet
        self.bar: Any = None
        if not self.quiet and self.stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=None, unit=unit, desc=desc, file=self.stream, dynamic_ncols=True)

    def update(self, done: int, total: int, note: str = "") -> None:
        """``done`` of ``total`` units; ``note`` (a rate, say) is appended to the line."""
        self.done, self.total, self.note = done, total, note
        if self.bar is not None:
            self.bar.total, self.bar.n = total, done
            self.bar.set_postfix_str(note, refresh=False)
            self.bar.refresh()
            return
        now = time.monotonic()
        if not self.quiet and now - self.last_line >= _interval():
            self.last_line = now
            self._line(now)

    def line(self, now: float | None = None) -> str:
        """The non-TTY progress line for the current state."""
        now = time.monotonic() if now is None else now
        elapsed = now - self.t0
        pct = 100.0 * self.done / self.total if self.total else 0.0
        left = ""
        if 0 < self.done < self.total:
            left = f", ~{elapsed * (self.total - self.done) / self.done:.0f} s left"
        return (
            f"{self.desc}: {pct:.1f} % ({self.done}/{self.total} {self.unit}s)"
            + (f", {self.note}" if self.note else "")
            + f", {elapsed:.0f} s elapsed{left}"
        )

    def _line(self, now: float) -> None:
        self.printed = (self.done, self.total)
        self.stream.write(self.line(now) + "\n")
        self.stream.flush()
        self.lines += 1

    def close(self) -> None:
        """Close the bar, or write the final line (when anything was counted)."""
        if self.bar is not None:
            self.bar.close()
        elif not self.quiet and self.total and self.printed != (self.done, self.total):
            self._line(time.monotonic())
