"""Connections, below the application: a header timeout and caps on open connections
(serve.header_timeout_s, serve.max_connections, serve.max_connections_per_client), and
the open-file limit they need.

uvicorn's h11 protocol times out idle keep-alive connections only: a connection that
sends half its headers (or nothing) is held for ever, and 1100 of them at `ulimit -n
1024` stop the service and flood the log with `Too many open files`. uvicorn's own
cap (limit_concurrency) answers a plain-text 503 and counts every client alike.
`guarded_protocol` is h11's protocol with a header timeout and two caps: a connection
whose request headers are not in within the header timeout is closed, and one opened
above a cap is given the service's JSON 503 naming the cap for its request instead of
the application. The service serves at most serve.max_connections connections, and at
most serve.max_connections_per_client of them from one client address, so that one
client cannot take every connection. At most REFUSING connections wait for their 503
at once; beyond them a new connection is closed at once, unanswered, so the open files
stay bounded whatever the clients do; `reserve_open_files` makes sure the bound is
below the process's limit before the service starts.
"""

from __future__ import annotations

import asyncio
import resource
from collections import Counter
from dataclasses import dataclass, field

from uvicorn.protocols.http.h11_impl import H11Protocol

from relocfw.core.errors import ConfigError
from relocfw.serve.guard import ASGIApp

# Connections over a cap that are still read and answered 503 (each for at most the
# header timeout); beyond them a new connection is closed at once.
REFUSING = 64
# The listening socket's backlog, which is also the most connections asyncio accepts in
# one turn of the loop before their protocols can close them: about three turns' worth
# may be open beyond the cap at once. (uvicorn's default of 2048 also lets one turn log
# 2048 tracebacks when accept() fails with `Too many open files`.)
ACCEPT_BACKLOG = 64
# Files the service holds besides its connections: the model, the listening socket,
# torch's and the worker processes' pipes, logs. Measured about 30; kept generous.
OTHER_FILES = 128


def open_files_needed(max_connections: int) -> int:
    """The open files a service with `max_connections` may hold at most."""
    return max_connections + REFUSING + 3 * ACCEPT_BACKLOG + OTHER_FILES


def reserve_open_files(max_connections: int) -> None:
    """Make sure this process may open the files `max_connections` need: raise the
    soft limit (ulimit -n) up to the hard one where it is lower, as nginx's
    worker_rlimit_nofile does.

    Raises:
        ConfigError: naming serve.max_connections when even the hard limit is too low,
            or the soft limit cannot be raised.
    """
    needed = open_files_needed(max_connections)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    above = (
        f"serve.max_connections={max_connections} needs up to {needed} open files, above "
        "this process's limit of"
    )
    if hard != resource.RLIM_INFINITY and hard < needed:
        most = hard - (needed - max_connections)
        # Where the service's other files alone pass the limit, no cap would help.
        lower = f"lower serve.max_connections to {most} or less, or " if most >= 1 else ""
        raise ConfigError(
            f"{above} {hard} (ulimit -n): {lower}raise the limit (ulimit -n {needed})"
        )
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))
    except (ValueError, OSError) as error:
        raise ConfigError(
            f"{above} {soft} (ulimit -n), which could not be raised ({error}): raise the "
            f"limit (ulimit -n {needed}) or lower serve.max_connections"
        ) from None


@dataclass(frozen=True)
class ConnectionCaps:
    """serve.max_connections and serve.max_connections_per_client (None: no cap)."""

    most: int
    most_per_client: int | None


@dataclass
class OpenConnections:
    """The connections a service holds: served (by client address) and refusing."""

    served: int = 0
    refusing: int = 0
    served_by_client: Counter[str | None] = field(default_factory=Counter)


# What a connection is to the counts: served, refused (answered 503), or closed at once.
SERVED, REFUSED, CLOSED = "served", "refused", "closed"


def guarded_protocol(
    header_timeout_s: float,
    caps: ConnectionCaps,
    over_capacity: ASGIApp,
    over_client_capacity: ASGIApp,
) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a header timeout and the connection caps; a
    connection over `caps.most` runs the ASGI app `over_capacity`, one over
    `caps.most_per_client` runs `over_client_capacity` (each a JSON 503 naming its
    key) instead of the service."""
    # This service's connections: the class is made once per service, so are they.
    connections = OpenConnections()

    class GuardedProtocol(H11Protocol):
        header_timer: asyncio.TimerHandle | None = None
        kind: str = CLOSED
        address: str | None = None

        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            super().connection_made(transport)  # type: ignore[arg-type]
            self.address = self.client[0] if self.client else None
            refusal = self.refusal()
            if refusal is None:
                self.kind = SERVED
                connections.served += 1
                connections.served_by_client[self.address] += 1
            elif connections.refusing < REFUSING:
                self.kind = REFUSED
                connections.refusing += 1
                self.app = refusal  # type: ignore[assignment]
            else:
                transport.abort()  # type: ignore[attr-defined]
                return
            self.wait_for_headers()

        def refusal(self) -> ASGIApp | None:
            """The 503 this new connection gets, or None: it is served."""
            per_client = caps.most_per_client
            if per_client is not None and connections.served_by_client[self.address] >= per_client:
                return over_client_capacity
            if connections.served >= caps.most:
                return over_capacity
            return None

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self.wait_for_headers()  # the next request on this connection

        def connection_lost(self, exc: Exception | None) -> None:
            self.stop_waiting()
            if self.kind == SERVED:
                connections.served -= 1
                connections.served_by_client[self.address] -= 1
                if connections.served_by_client[self.address] <= 0:
                    del connections.served_by_client[self.address]  # bounded by the open
            elif self.kind == REFUSED:
                connections.refusing -= 1
            self.kind = CLOSED
            super().connection_lost(exc)

        def wait_for_headers(self) -> None:
            self.stop_waiting()
            self.header_timer = self.loop.call_later(header_timeout_s, self.headers_overdue)

        def stop_waiting(self) -> None:
            if self.header_timer is not None:
                self.header_timer.cancel()
                self.header_timer = None

        def headers_overdue(self) -> None:
            """Close the connection if no request's head came since it opened or since
            its last answer (a request whose head is in has the application's body
            timeout instead). Not logged: a line each would let a flood of such
            clients flood the log."""
            self.header_timer = None
            between_requests = self.cycle is None or self.cycle.response_complete
            if between_requests and not self.transport.is_closing():
                self.transport.close()

    return GuardedProtocol
