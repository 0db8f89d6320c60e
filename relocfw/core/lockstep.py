"""Many queries' searches in lockstep: their network calls merged, run on one thread.

A crop search is plain sequential code that calls its distance function a few times
(the GA once per generation). To batch the candidates of B queries into one forward
pass without changing any search, each query's search runs in a thread of its own
and every network call goes to a Lockstep. Once each query still running has asked
(or finished), the serving thread answers all of them from one merged call.

Every network pass, merged or not (shared scoring's strip pass goes through `call`),
runs on the one serving thread, the caller's. With OpenMP every thread that enters
torch gets a team of workers of its own, and idle teams spin: passes made from 16
search threads left 16 teams fighting for 2 cores and made batching slower than one
query at a time. What a search computes between its calls (the GA's breeding) runs
in its own thread.

An interrupt (Ctrl-C, or any BaseException that is not an Exception) on the serving
thread is never handed to the members: `serve` cancels them, so each waiting search
ends at once with `Cancelled`, and re-raises the interrupt to its caller.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any


class Cancelled(BaseException):
    """Raised in a member whose lockstep stopped serving (the serving thread was
    interrupted). A BaseException, like KeyboardInterrupt, so that a search's own
    `except Exception` cannot swallow it and ask again."""


class Lockstep:
    """Gathers one request from each running member, answers them all in one call.

    Members (search threads) call `ask` or `call` and `leave`; one thread, the one that
    owns the network, calls `serve` until every member has left. An ordinary error of
    a merged call goes to the members that asked; an interrupt stops `serve` and
    cancels every member (see the module's docstring).

    Args:
        members: how many threads take part; each calls `leave` when it is done.
        run_together: requests -> their answers, in order; one merged call.
    """

    def __init__(
        self, members: int, run_together: Callable[[Sequence[Any]], Sequence[Any]]
    ) -> None:
        self._condition = threading.Condition()
        self._running = members
        self._pending: dict[int, Any] = {}
        self._solo: deque[tuple[int, Callable[[], Any]]] = deque()
        self._answers: dict[int, Any] = {}
        self._cancelled = False
        self._run_together = run_together
        self.calls = 0  # merged calls made: what batching saved is visible

    def ask(self, member: int, request: Any) -> Any:
        """The answer to `request`, once every running member has asked too."""
        with self._condition:
            self._pending[member] = request
            self._condition.notify_all()
        return self._answer_of(member)

    def call(self, member: int, work: Callable[[], Any]) -> Any:
        """`work()`, run on the serving thread as soon as it is free (not merged)."""
        with self._condition:
            self._solo.append((member, work))
            self._condition.notify_all()
        return self._answer_of(member)

    def leave(self, member: int) -> None:
        """`member` asks nothing more: the others no longer wait for it."""
        with self._condition:
            self._running -= 1
            self._condition.notify_all()

    def cancel(self) -> None:
        """Every member waiting for an answer, or asking later, gets `Cancelled`."""
        with self._condition:
            self._cancelled = True
            self._condition.notify_all()

    def serve(self) -> None:
        """Answer the members' calls on this thread until every member has left.

        An interrupt (e.g. KeyboardInterrupt, while waiting or during a call) cancels
        the members and is re-raised here at once.
        """
        try:
            self._serve_until_all_left()
        except BaseException:
            self.cancel()
            raise

    def _serve_until_all_left(self) -> None:
        while True:
            with self._condition:
                while not (self._solo or self._merge_ready() or self._running == 0):
                    self._condition.wait()
                if self._solo:
                    member, work = self._solo.popleft()
                    members, requests = [member], None
                elif self._merge_ready():
                    members, requests = zip(*self._pending.items(), strict=True)
                    self._pending = {}
                    self.calls += 1
                else:
                    return  # every member has left and nothing is queued
            try:
                solo = requests is None
                answers = [work()] if solo else list(self._run_together(list(requests)))
            except Exception as error:  # noqa: BLE001 - handed to every asker, re-raised there
                # (an interrupt is not an Exception: it leaves serve, see above)
                answers = [_Failed(error)] * len(members)
            with self._condition:
                self._answers.update(zip(members, answers, strict=True))
                self._condition.notify_all()

    def _merge_ready(self) -> bool:
        # A member inside `call` has not asked yet, so a merge waits for it.
        return bool(self._pending) and len(self._pending) >= self._running

    def _answer_of(self, member: int) -> Any:
        with self._condition:
            while member not in self._answers and not self._cancelled:
                self._condition.wait()
            if self._cancelled:
                raise Cancelled("the serving thread stopped (interrupted)")
            answer = self._answers.pop(member)
        if isinstance(answer, _Failed):
            raise answer.error
        return answer


class _Failed:
    def __init__(self, error: BaseException) -> None:
        self.error = error


# How long an interrupted group waits for its search threads to end: a cancelled
# search ends at its next network call, within milliseconds unless it computes long
# between calls; a thread still running after this is a daemon and is left behind.
INTERRUPTED_JOIN_SECONDS = 2.0


def join_within(threads: Sequence[threading.Thread], seconds: float) -> None:
    """Join `threads`, waiting at most `seconds` for all of them together."""
    deadline = time.monotonic() + seconds
    for thread in threads:
        thread.join(max(0.0, deadline - time.monotonic()))


def first_failure(failures: dict[int, BaseException]) -> BaseException:
    """The error a group raises: an interrupt (KeyboardInterrupt, SystemExit: not an
    Exception) wins over any member's ordinary error, else the first query's error,
    whatever the timing."""
    interrupts = [m for m, error in failures.items() if not isinstance(error, Exception)]
    return failures[min(interrupts or failures)]
