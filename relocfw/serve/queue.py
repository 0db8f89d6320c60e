"""The bounded queue in front of the workers (serve.max_pending).

A request takes its place once its whole body is in (a client that sends its body
slowly, or never, holds none) and holds it until its worker is done with its query,
whether or not its caller still waits: the count covers the images being decoded and
what the workers owe, so the bound holds for both. One more than
max_pending is refused at once (QueueFullError, answered 503 with Retry-After), never
kept in an unbounded backlog. A caller that disconnects while its query waits takes
the query out (it never runs); one whose query already runs leaves it to finish,
unread.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

from relocfw.core.values import Localization
from relocfw.serve.workers import Query, Workers


class QueueFullError(Exception):
    """max_pending queries are admitted already."""


class WorkersLostError(Exception):
    """A worker process ended while the service runs (killed, e.g. out of memory): its
    pool answers no more queries (answered 503)."""

    def __init__(self) -> None:
        super().__init__(
            "a worker process of the service has ended (killed, or out of memory?): "
            "it answers no more queries until it is restarted"
        )


@dataclass
class QueueCounts:
    """What the service has done, for GET /v1/health.

    Attributes:
        pending: queries holding a place: being decoded, waiting or running.
        answered: queries answered (200).
        refused: requests answered with a refusal, a 4xx or a 503, by any layer
            (counted by relocfw.serve.guard).
        abandoned: queries whose caller left before the answer.
    """

    pending: int = 0
    answered: int = 0
    refused: int = 0
    abandoned: int = 0


class QueryQueue:
    """Admits at most `max_pending` queries at once and hands them to the workers.

    Used from the event loop's thread only, so its counts need no lock; the workers'
    completions come back to it through the loop.
    """

    def __init__(self, workers: Workers, max_pending: int) -> None:
        self.workers = workers
        self.max_pending = max_pending
        self.counts = QueueCounts()

    def reserve(self) -> None:
        """Take a place for a request whose body is in, before it is decoded, so the
        images being decoded count against max_pending too; the place goes to its
        job (`run`) or back (`release`).

        Raises:
            QueueFullError: max_pending places are taken.
        """
        if self.counts.pending >= self.max_pending:
            raise QueueFullError
        self.counts.pending += 1

    async def run(self, query: Query, client_left: Awaitable[None]) -> Localization | None:
        """The answer to a query that holds a place (`reserve`), or None when the caller
        left before it came; the place is freed when the job is done, not before.

        Raises:
            WorkersLostError: a worker process has ended (serve.workers > 1).
        """
        loop = asyncio.get_running_loop()
        try:
            job = self.workers.submit(query)
        except BaseException as error:  # no job holds the place
            self.release()
            if isinstance(error, BrokenProcessPool):
                raise WorkersLostError from None
            raise
        job.add_done_callback(lambda _: self.release_from(loop))
        answer = asyncio.wrap_future(job)
        watch = asyncio.ensure_future(client_left)
        try:
            done, _ = await asyncio.wait({answer, watch}, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            answer.cancel()
            raise
        finally:
            watch.cancel()
        if answer in done:
            try:
                localization = answer.result()
            except BrokenProcessPool:
                raise WorkersLostError from None
            self.counts.answered += 1
            return localization
        answer.cancel()  # cancels the job too where it has not started
        self.counts.abandoned += 1
        return None

    def release_from(self, loop: asyncio.AbstractEventLoop) -> None:
        """A job is done (answered, failed or cancelled): free its place, on the loop."""
        # A closed loop: the service is gone, there is nothing left to count.
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self.release)

    def release(self) -> None:
        """Free a place: its job is done, or its request ended before it had one."""
        self.counts.pending -= 1
