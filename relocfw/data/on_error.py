"""What to do with a bad entry in bulk data: stop (default) or skip and report it."""

from __future__ import annotations

from relocfw.core.errors import ConfigError, DataError


class OnError:
    """The `dataset.on_error` rule.

    "fail" stops at the first bad file or line with its message. "skip" leaves the
    entry out, keeps its message in `skipped`, and the CLI writes them all to
    skipped.txt in the run directory: nothing is left out silently.
    """

    def __init__(self, mode: str = "fail") -> None:
        if mode not in ("fail", "skip"):
            raise ConfigError(f"dataset.on_error must be 'fail' or 'skip', got {mode!r}")
        self.mode = mode
        self.skipped: list[str] = []

    def handle(self, error: DataError) -> None:
        """Raise `error`, or record it and return so the caller moves on."""
        if self.mode == "fail":
            raise error
        self.skipped.append(str(error))
