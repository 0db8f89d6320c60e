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
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any


class Lockstep:
    """Gathers one request from each running member, answers them all in one call.

    Members (search threads) call `ask` or `call` and `leave`; one thread, the one that
    owns the network, calls `serve` until every member has left.

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

    def serve(self) -> None:
        """Answer the members' calls on this thread until every member has left."""
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
            except BaseException as error:  # noqa: BLE001 - handed to every asker, re-raised there
                answers = [_Failed(error)] * len(members)
            with self._condition:
                self._answers.update(zip(members, answers, strict=True))
                self._condition.notify_all()

    def _merge_ready(self) -> bool:
        # A member inside `call` has not asked yet, so a merge waits for it.
        return bool(self._pending) and len(self._pending) >= self._running

    def _answer_of(self, member: int) -> Any:
        with self._condition:
            while member not in self._answers:
                self._condition.wait()
            answer = self._answers.pop(member)
        if isinstance(answer, _Failed):
            raise answer.error
        return answer


class _Failed:
    def __init__(self, error: BaseException) -> None:
        self.error = error
