"""A dependency-free progress bar on stderr."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Counts work done and redraws one line at most ten times a second.

    Args:
        total: units of work expected.
        label: what is being done, shown before the bar.
        quiet: draw nothing (tests, library use).
        stream: where to draw; stderr keeps stdout clean for tables.
    """

    def __init__(
        self, total: int, label: str, quiet: bool = False, stream: TextIO | None = None
    ) -> None:
        self.total = max(1, total)
        self.label = label
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.done = 0
        self.start = time.perf_counter()
        self.last_draw = 0.0
        self.suffix = ""
        # A log file or CI gets a line per quarter, not hundreds of carriage returns.
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.next_milestone = 0.25

    def advance(self, count: int = 1, suffix: str | None = None) -> None:
        self.done += count
        if suffix is not None:
            self.suffix = suffix
        if self.quiet:
            return
        now = time.perf_counter()
        if self.interactive:
            if now - self.last_draw > 0.1 or self.done >= self.total:
                self.last_draw = now
                self._draw(now)
        elif self.done / self.total >= self.next_milestone:
            self.next_milestone += 0.25
            self._draw(now)

    def _draw(self, now: float) -> None:
        fraction = min(1.0, self.done / self.total)
        elapsed = now - self.start
        remaining = elapsed / fraction - elapsed if fraction > 0 else 0.0
        bar = "#" * int(fraction * 24)
        line = (
            f"{self.label} [{bar:<24}] {self.done}/{self.total} "
            f"{elapsed:5.0f}s elapsed, {remaining:4.0f}s left {self.suffix}"
        )
        self.stream.write(f"\r{line}\033[K" if self.interactive else line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.quiet:
            return
        if self.interactive:
            self._draw(time.perf_counter())
            self.stream.write("\n")
        elif self.next_milestone <= 1.0:  # the last milestone was not drawn yet
            self._draw(time.perf_counter())
        self.stream.flush()
