"""Progress of long work on stderr: a tqdm bar on a terminal, plain lines elsewhere."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm


class Progress:
    """Counts work done and shows it.

    On a terminal, a tqdm bar (rate, elapsed and remaining time). Anywhere else (a log
    file, CI) one plain line per quarter of the work, not hundreds of carriage returns.

    Args:
        total: units of work expected.
        label: what is being done, shown before the bar.
        quiet: show nothing (tests, library use).
        stream: where to write; stderr keeps stdout clean for tables.
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
        self.suffix = ""
        self.next_milestone = 0.25
        interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar: tqdm | None = None
        if interactive and not quiet:
            self.bar = tqdm(total=self.total, desc=label, file=self.stream, leave=True)

    def advance(self, count: int = 1, suffix: str | None = None) -> None:
        self.done += count
        if suffix is not None:
            self.suffix = suffix
        if self.quiet:
            return
        if self.bar is not None:
            if suffix is not None:
                self.bar.set_postfix_str(suffix, refresh=False)
            self.bar.update(count)
        elif self.done / self.total >= self.next_milestone:
            while self.done / self.total >= self.next_milestone:
                self.next_milestone += 0.25
            self._line()

    def _line(self) -> None:
        elapsed = time.perf_counter() - self.start
        fraction = min(1.0, self.done / self.total)
        remaining = elapsed / fraction - elapsed if fraction > 0 else 0.0
        self.stream.write(
            f"{self.label}: {self.done}/{self.total} ({fraction:.0%}), {elapsed:.0f}s elapsed, "
            f"{remaining:.0f}s left {self.suffix}".rstrip()
            + "\n"
        )
        self.stream.flush()

    def close(self) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.close()
        elif self.next_milestone <= 1.0:  # the last milestone was not written yet
            self._line()
