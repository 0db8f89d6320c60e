"""The bytes of request bodies the service holds while they arrive.

A request takes its queue place (serve.max_pending) only once its whole body is in,
so that silent clients hold no place. The bodies still arriving are bounded here
instead: by the bytes actually received, not by what Content-Length announces, so a
client that announces a large body and sends nothing holds nothing, and one that sends
most of a large body slowly holds what it sent until serve.body_timeout_s ends it. The
budget is serve.max_pending x serve.max_bytes: the memory the queue's places could
hold in bodies.
"""

from __future__ import annotations

from relocfw.core.errors import DataError


class BodyBudgetError(DataError):
    """The bodies arriving at once would pass the budget (answered 503)."""


class BodyBudget:
    """Counts the bytes of bodies being received; refuses a chunk that would pass `most`.

    Used from the event loop's thread only (bodies are read there), so it needs no lock.
    """

    def __init__(self, most: int) -> None:
        self.most = most
        self.held = 0

    def take(self, size: int) -> None:
        """Hold `size` more bytes, or raise BodyBudgetError holding nothing more."""
        if self.held + size > self.most:
            raise BodyBudgetError(
                f"the service is receiving {self.held} bytes of request bodies already, "
                f"and {size} more would pass serve.max_pending x serve.max_bytes = "
                f"{self.most}; retry after the Retry-After seconds"
            )
        self.held += size

    def give_back(self, size: int) -> None:
        """A body is in (its queue place holds it now) or dropped: free its bytes."""
        self.held -= size
