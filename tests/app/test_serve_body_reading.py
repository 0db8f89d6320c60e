"""Reading a request's body in the service (relocfw.serve.app.read_body_in_time), in
process: what the body timeout needs from Python (pyproject: requires-python >= 3.10)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from starlette.requests import Request

from relocfw.serve.app import BodyTimeoutError, read_body_in_time
from relocfw.serve.body_budget import BodyBudget
from relocfw.serve.settings import ServeSettings


def silent_request() -> Request:
    """A POST whose headers are in and whose body never comes."""
    scope = {
        "type": "http",
        "method": "POST",
        "path": "/v1/localize",
        "headers": [(b"content-length", b"1000")],
        "query_string": b"",
    }

    async def receive() -> dict:
        await asyncio.Event().wait()  # never set: no byte of the body ever comes
        return {}

    return Request(scope, receive)


def test_the_body_timeout_needs_nothing_newer_than_python_3_10(monkeypatch):
    """asyncio.timeout came in Python 3.11: the service must time bodies out without it."""
    monkeypatch.delattr(asyncio, "timeout", raising=False)
    settings = ServeSettings(model=Path("m.relocfw"), body_timeout_s=0.05)
    budget = BodyBudget(10_000)
    with pytest.raises(BodyTimeoutError, match=r"serve\.body_timeout_s=0\.05 seconds"):
        asyncio.run(read_body_in_time(silent_request(), settings, budget))
    assert budget.held == 0
