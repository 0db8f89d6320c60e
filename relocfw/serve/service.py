"""Serving a loaded model: the socket, uvicorn, and a clean end on SIGTERM.

SIGTERM (or Ctrl-C) stops accepting connections; uvicorn lets the requests in flight
finish and answers them, then the application's lifespan waits for the workers, and
the process exits 0.
"""

from __future__ import annotations

import signal
import socket
import sys
from concurrent.futures.process import BrokenProcessPool
from types import FrameType

import uvicorn

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.pipeline import Relocalizer
from relocfw.serve.answers import describe_model
from relocfw.serve.app import Service, create_app
from relocfw.serve.auth import BearerToken
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
    listener.listen(128)
    return listener


def url_of(listener: socket.socket) -> str:
    host, port = listener.getsockname()[:2]
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


def after_drain(signum: int, frame: FrameType | None) -> None:
    """SIGTERM's handler while serving: uvicorn catches the signal itself, drains, and
    raises it again once done so that the handler before it runs; this one lets the
    process end as a finished run (exit 0) instead of dying of the signal."""


def run_service(settings: ServeSettings, relocalizer: Relocalizer, loader: Loader) -> None:
    """Serve `relocalizer` (loaded from settings.model) until SIGTERM or Ctrl-C.

    Args:
        loader: builds the same Relocalizer again, in each worker process
            (serve.workers > 1); picklable.

    Raises:
        ConfigError: the token file cannot be used, or host:port cannot be bound.
    """
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
    app = create_app(Service(settings, queue, info, token))
    config = uvicorn.Config(
        app,
        log_level="info",
        access_log=False,
        lifespan="on",
        timeout_graceful_shutdown=None,  # a query in flight is always finished
    )
    server = uvicorn.Server(config)
    print(
        f"relocfw serve: {url_of(listener)} (model {info.file_name}, id {info.model_id}, "
        f"{settings.workers} worker(s), token {'on' if token else 'off'})",
        flush=True,
    )
    before = signal.signal(signal.SIGTERM, after_drain)
    try:
        server.run(sockets=[listener])
    finally:
        signal.signal(signal.SIGTERM, before)
        listener.close()
    print("relocfw serve: stopped", file=sys.stderr, flush=True)
