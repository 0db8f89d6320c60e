"""The ASGI layer around the application: how every request ends, whichever layer
answers it.

- Every refusal (a 4xx, or a 503) is counted for GET /v1/health's `refused`: the
  application's own, FastAPI's (404, 405) and the connection cap's.
- A request still open when the shutdown's time is up (serve.shutdown_timeout_s after
  SIGTERM) is cancelled by uvicorn; it is answered 503 and logged in one line instead
  of uvicorn's traceback of the cancellation.
- `over_capacity` is the JSON 503 a connection above serve.max_connections or
  serve.max_connections_per_client gets (relocfw.serve.connections).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.responses import JSONResponse

from relocfw.serve.queue import QueueCounts

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

# nginx's "client closed request": never sent (the client is gone), not a refusal.
CLIENT_LEFT = 499
SERVICE_UNAVAILABLE = 503
# uvicorn's log: the service's lines appear among its own, in its format.
LOG = logging.getLogger("uvicorn.error")


def is_refusal(status: int) -> bool:
    return (400 <= status < 500 and status != CLIENT_LEFT) or status == SERVICE_UNAVAILABLE


def refusal(
    status: int, message: str, headers: dict[str, str] | None = None, close: bool = False
) -> JSONResponse:
    """{"error": message}; `close`: the connection is closed after it (its request's
    body was not read to its end, or the connection is refused)."""
    headers = dict(headers or {})
    if close:
        headers["Connection"] = "close"
    return JSONResponse({"error": message}, status_code=status, headers=headers)


class Guarded:
    """`app` with its refusals counted in `counts` and its cancelled requests answered."""

    def __init__(self, app: ASGIApp, counts: QueueCounts, shutdown_timeout_s: float) -> None:
        self.app = app
        self.counts = counts
        self.shutdown_timeout_s = shutdown_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def counted(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                if is_refusal(message["status"]):
                    self.counts.refused += 1
            await send(message)

        try:
            await self.app(scope, receive, counted)
        except asyncio.CancelledError:
            # Only uvicorn's shutdown cancels a request; the task ends here, answered.
            LOG.warning(
                "relocfw serve: %s %s was still open serve.shutdown_timeout_s=%g s after the "
                "stop: answered 503",
                scope.get("method"),
                scope.get("path"),
                self.shutdown_timeout_s,
            )
            if not started:
                stopping = refusal(SERVICE_UNAVAILABLE, "the service is stopping", close=True)
                await stopping(scope, receive, counted)


def over_capacity(message: str, retry_after_s: int) -> ASGIApp:
    """The app a connection above a connection cap runs: a JSON 503 with `message`
    (which names the cap's key), and the connection closed after it."""
    answer = refusal(SERVICE_UNAVAILABLE, message, {"Retry-After": str(retry_after_s)}, close=True)

    async def refuse(scope: Scope, receive: Receive, send: Send) -> None:
        await answer(scope, receive, send)

    return refuse
