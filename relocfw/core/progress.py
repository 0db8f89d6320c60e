"""Progress of long work on stderr: a tqdm bar on a terminal, plain lines elsewhere."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm


class Progress:
    """Counts work done and shows it.

    On a terminal, a tqdm bar (rate, elapsed and remaining time). Anywhere else (a log
    file, CI) one plain line per quarter of the work, not hundreds of carriage returns;
    when the total is unknown (a stream), one line every LINE_EVERY_S seconds instead.

    Args:
        total: units of work expected; None when unknown (a video or bag that does
            not say how many frames it holds).
        label: what is being done, shown before the bar.
        quiet: show nothing (tests, library use).
        stream: where to write; stderr keeps stdout clean for tables.
        unit: the name of one unit of work (e.g. "frame"): the bar counts in it and
            plain lines add the rate, units per second. None: plain lines as before.
    """

    LINE_EVERY_S = 30.0

    def __init__(
        self,
        total: int | None,
        label: str,
        quiet: bool = False,
        stream: TextIO | None = None,
        unit: str | None = None,
    ) -> None:
        self.total = None if total is None else max(1, total)
        self.label = label
        self.quiet = quiet
        self.stream = stream or sys.stderr
        self.unit = unit
        self.done = 0
        self.start = time.perf_counter()
        self.last_line = self.start
        self.suffix = ""
        self.next_milestone = 0.25
        interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar: tqdm | None = None
        if interactive and not quiet:
            self.bar = tqdm(
                total=self.total, desc=label, file=self.stream, leave=True, unit=unit or "it"
            )

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
        elif self.total is None:
            if time.perf_counter() - self.last_line >= self.LINE_EVERY_S:
                self._line()
        elif self.done / self.total >= self.next_milestone:
            while self.done / self.total >= self.next_milestone:
                self.next_milestone += 0.25
            self._line()

    def _line(self) -> None:
        now = time.perf_counter()
        self.last_line = now
        elapsed = now - self.start
        rate = f", {self.done / elapsed:.1f} {self.unit}/s" if self.unit and elapsed > 0 else ""
        if self.total is None:
            counted = f"{self.done} {self.unit or 'done'}, {elapsed:.0f}s elapsed{rate}"
        else:
            fraction = min(1.0, self.done / self.total)
            remaining = elapsed / fraction - elapsed if fraction > 0 else 0.0
            counted = (
                f"{self.done}/{self.total} ({fraction:.0%}), {elapsed:.0f}s elapsed, "
                f"{remaining:.0f}s left{rate}"
            )
        self.stream.write(f"{self.label}: {counted} {self.suffix}".rstrip() + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.close()
        elif self.total is None or self.next_milestone <= 1.0:  # the last line is not written
            self._line()
