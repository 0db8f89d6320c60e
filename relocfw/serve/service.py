"""Serving a loaded model: the socket, uvicorn, and a clean end on SIGTERM.

SIGTERM or Ctrl-C (SIGINT) stops accepting connections and closes the idle ones;
uvicorn lets the requests in flight finish and answers them for up to
serve.shutdown_timeout_s, answers the ones still open then 503 (relocfw.serve.guard),
the application's lifespan waits for the query running in a worker, and the process
exits 0. Connections get a header timeout and caps (relocfw.serve.connections).
"""

from __future__ import annotations

import ipaddress
import signal
import socket
import sys
from concurrent.futures.process import BrokenProcessPool
from types import FrameType

import uvicorn

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.pipeline import Relocalizer
from relocfw.serve.answers import describe_model
from relocfw.serve.app import Service, over_capacity_app, served_app
from relocfw.serve.auth import BearerToken
from relocfw.serve.connections import (
    ACCEPT_BACKLOG,
    ConnectionCaps,
    guarded_protocol,
    reserve_open_files,
)
from relocfw.serve.queue import QueryQueue
from relocfw.serve.settings import ServeSettings
from relocfw.serve.workers import Loader, Workers


def listening_socket(host: str, port: int) -> socket.socket:
    """A socket bound and listening on host:port (port 0: a free one).

    Raises:
        ConfigError: naming serve.host / serve.port when it cannot be bound.
    """
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, protocol, _, address = found[0]
        listener = socket.socket(family, kind, protocol)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(address)
    except OSError as error:
        raise ConfigError(
            f"cannot listen on serve.host={host} serve.port={port}: {error.strerror or error}"
        ) from error
    listener.listen(ACCEPT_BACKLOG)
    return listener


def url_of(listener: socket.socket) -> str:
    host, port = listener.getsockname()[:2]
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


# The signals that stop the service after a drain: a supervisor's and Ctrl-C.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def exposure_warning(host: str, token: bool) -> str | None:
    """One line to print when the service listens beyond this machine (`host`: the
    bound address) without a token; None otherwise."""
    try:
        loopback = ipaddress.ip_address(host.split("%")[0]).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if loopback or token:
        return None
    return (
        f"warning: serve.host={host} accepts connections from other machines and no "
        "serve.token_file is set: anyone who reaches the port can use the service"
    )


def check_open_files(settings: ServeSettings) -> None:
    """Before loading anything: the open files serve.max_connections needs are allowed
    (the soft limit raised where needed), or a ConfigError naming the key."""
    reserve_open_files(settings.max_connections)


def after_drain(signum: int, frame: FrameType | None) -> None:
    """SIGTERM's and SIGINT's handler while serving: uvicorn catches the signal itself,
    drains, and raises it again once done so that the handler before it runs; this one
    lets the process end as a finished run (exit 0) instead of dying of the signal or
    raising KeyboardInterrupt."""


def run_service(settings: ServeSettings, relocalizer: Relocalizer, loader: Loader) -> None:
    """Serve `relocalizer` (loaded from settings.model) until SIGTERM or Ctrl-C.

    Args:
        loader: builds the same Relocalizer again, in each worker process
            (serve.workers > 1); picklable.

    Raises:
        ConfigError: the token file cannot be used, host:port cannot be bound, or the
            open files serve.max_connections needs are not allowed.
    """
    check_open_files(settings)
    token = BearerToken.from_file(settings.token_file) if settings.token_file else None
    info = describe_model(relocalizer, settings.model)
    listener = listening_socket(settings.host, settings.port)
    workers = Workers(relocalizer, loader, settings.workers)
    try:
        workers.warm()
    except BrokenProcessPool as error:
        listener.close()
        raise DataError(
            f"a worker process could not load serve.model={settings.model} (its error is above)"
        ) from error
    queue = QueryQueue(workers, settings.max_pending)
    service = Service(settings, queue, info, token, relocalizer.options.max_aspect)
    protocol = guarded_protocol(
        settings.header_timeout_s,
        ConnectionCaps(settings.max_connections, settings.max_connections_per_client),
        over_capacity_app(service, "max_connections"),
        over_capacity_app(service, "max_connections_per_client"),
    )
    config = uvicorn.Config(
        served_app(service),
        http=protocol,
        backlog=ACCEPT_BACKLOG,
        log_level="info",
        access_log=False,
        lifespan="on",
        # Then the requests still open are answered 503; the query running in a
        # worker is still finished (the lifespan's end waits for it).
        timeout_graceful_shutdown=settings.shutdown_timeout_s,  # type: ignore[arg-type]
        # An idle keep-alive connection waits for its next request's head: one timeout.
        timeout_keep_alive=settings.header_timeout_s,  # type: ignore[arg-type]
    )
    server = uvicorn.Server(config)
    warning = exposure_warning(listener.getsockname()[0], token is not None)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    print(
        f"relocfw serve: {url_of(listener)} (model {info.file_name}, id {info.model_id}, "
        f"{settings.workers} worker(s), token {'on' if token else 'off'})",
        flush=True,
    )
    before = {stop: signal.signal(stop, after_drain) for stop in STOP_SIGNALS}
    try:
        server.run(sockets=[listener])
    finally:
        for stop, handler in before.items():
            signal.signal(stop, handler)
        listener.close()
    print("relocfw serve: stopped", file=sys.stderr, flush=True)
