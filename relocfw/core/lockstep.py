"""Many queries' searches in lockstep: their network calls merged into one.

A crop search is plain sequential code that calls its distance function a few times
(the GA once per generation). To batch the candidates of B queries into one forward
pass without changing any search, each query's search runs in a thread of its own
and every network call goes to a Lockstep. It waits until each query still running
has asked (or finished), then answers all of them from one merged call, made while
every thread waits, so it runs alone with all of torch's intra-op threads. What a
search computes between its calls (the GA's breeding, shared scoring's strip pass,
which the pipeline serialises with a lock of its own) runs in its thread.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any


class Lockstep:
    """Gathers one request from each running member, answers them all in one call.

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
        self._answers: dict[int, Any] = {}
        self._run_together = run_together
        self.calls = 0  # merged calls made: what batching saved is visible

    def ask(self, member: int, request: Any) -> Any:
        """The answer to `request`, once every running member has asked too."""
        with self._condition:
            self._pending[member] = request
            self._run_if_all_asked()
            while member not in self._answers:
                self._condition.wait()
            answer = self._answers.pop(member)
        if isinstance(answer, _Failed):
            raise answer.error
        return answer

    def leave(self, member: int) -> None:
        """`member` asks nothing more: the others no longer wait for it."""
        with self._condition:
            self._running -= 1
            self._run_if_all_asked()

    def _run_if_all_asked(self) -> None:
        if not self._pending or len(self._pending) < self._running:
            return
        members, requests = zip(*self._pending.items(), strict=True)
        self._pending = {}
        self.calls += 1
        try:
            answers = list(self._run_together(list(requests)))
        except BaseException as error:  # noqa: BLE001 - handed to every asker, re-raised there
            answers = [_Failed(error)] * len(members)
        self._answers.update(zip(members, answers, strict=True))
        self._condition.notify_all()


class _Failed:
    def __init__(self, error: BaseException) -> None:
        self.error = error
