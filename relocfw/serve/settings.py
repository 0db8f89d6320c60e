"""The serve.* options (conf/config.yaml), checked once before anything is loaded."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relocfw.core.errors import ConfigError

# A bound on decoded pixels, below imaging.MAX_IMAGE_PIXELS (2^30, 3 GiB as RGB): a
# 20 MB PNG may announce 30000 x 30000 pixels, and a service decodes many requests
# at once. 50 MP is well above any robot camera.
DEFAULT_MAX_PIXELS = 50_000_000
# A few seconds: a request's headers are a few hundred bytes, and a robot's image (a
# few MB at most) crosses a slow Wi-Fi link in well under the body's time. A client
# slower than that holds a connection (and its place) that a real caller needs.
DEFAULT_HEADER_TIMEOUT_S = 5.0
DEFAULT_BODY_TIMEOUT_S = 10.0
# After SIGTERM: long enough for the queue's queries on a CPU (max_pending of a few
# hundred ms each) and a body still on its way, short enough for a supervisor.
DEFAULT_SHUTDOWN_TIMEOUT_S = 10.0
# Far above what max_pending queries need, far below the usual 1024 open files.
DEFAULT_MAX_CONNECTIONS = 256
# One address's share: a browser opens 6 connections to a host, a robot a few; 32
# leaves room for a few processes behind one NAT, and 8 such addresses short of the cap.
DEFAULT_MAX_CONNECTIONS_PER_CLIENT = 32


def whole_number(key: str, value: Any, least: int, most: int | None = None) -> int:
    """`value` as an int in [least, most], or a ConfigError naming serve.KEY."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"serve.{key} must be a whole number, got {value!r}")
    if value < least or (most is not None and value > most):
        bound = f">= {least}" if most is None else f"in [{least}, {most}]"
        raise ConfigError(f"serve.{key} must be {bound}, got {value}")
    return value


def seconds(key: str, value: Any) -> float:
    """`value` as a finite number of seconds > 0, or a ConfigError naming serve.KEY."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"serve.{key} must be a number > 0 (seconds), got {value!r}")
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(f"serve.{key} must be a number > 0 (seconds), got {value}")
    return float(value)


@dataclass(frozen=True)
class ServeSettings:
    """What the service runs and how much it takes in.

    Attributes:
        model: the model file (task=relocalize's model.relocfw).
        host: the address to bind: 127.0.0.1 (this machine only) unless set.
        port: the TCP port.
        workers: processes that each hold the model and answer one query at a time
            (1: one thread of the server process).
        max_pending: queries admitted at once, waiting or running; one more is
            answered 503 with Retry-After.
        max_bytes: the largest request body (413 above it).
        max_pixels: the most pixels an image header may announce (400 above it).
        token_file: a file holding the bearer token callers must send; None: no token.
        retry_after_s: the Retry-After a 503 carries.
        header_timeout_s: the seconds a connection has to send a request's headers
            after it opened or after its last answer (closed after them): also how
            long an idle keep-alive connection is kept.
        body_timeout_s: the seconds a request has to send its whole body once its
            headers are in, a deadline for the whole body (answered 408 and closed
            after them); its queue place is taken only once the body is in.
        shutdown_timeout_s: the seconds after SIGTERM (or Ctrl-C) that the requests
            in flight have to finish; the ones left are answered 503.
        max_connections: the connections served at once; one more is answered 503.
        max_connections_per_client: the connections one client address is served at
            once; one more from it is answered 503. None: no such cap (behind a proxy,
            every connection comes from the proxy's address).
    """

    model: Path
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int = 1
    max_pending: int = 8
    max_bytes: int = 20_000_000
    max_pixels: int = DEFAULT_MAX_PIXELS
    token_file: Path | None = None
    retry_after_s: int = 1
    header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S
    body_timeout_s: float = DEFAULT_BODY_TIMEOUT_S
    shutdown_timeout_s: float = DEFAULT_SHUTDOWN_TIMEOUT_S
    max_connections: int = DEFAULT_MAX_CONNECTIONS
    max_connections_per_client: int | None = DEFAULT_MAX_CONNECTIONS_PER_CLIENT

    def __post_init__(self) -> None:
        if not str(self.host).strip():
            raise ConfigError("serve.host is empty: pass an address, e.g. serve.host=127.0.0.1")
        whole_number("port", self.port, 0, 65535)
        whole_number("workers", self.workers, 1)
        whole_number("max_pending", self.max_pending, 1)
        whole_number("max_bytes", self.max_bytes, 1)
        whole_number("max_pixels", self.max_pixels, 1)
        whole_number("retry_after_s", self.retry_after_s, 0)
        whole_number("max_connections", self.max_connections, 1)
        if self.max_connections_per_client is not None:
            whole_number("max_connections_per_client", self.max_connections_per_client, 1)
        for key in ("header_timeout_s", "body_timeout_s", "shutdown_timeout_s"):
            object.__setattr__(self, key, seconds(key, getattr(self, key)))
        if self.max_pending < self.workers:
            raise ConfigError(
                f"serve.max_pending={self.max_pending} is below serve.workers="
                f"{self.workers}: some workers could never be given a query"
            )
        if self.max_connections < self.max_pending:
            raise ConfigError(
                f"serve.max_connections={self.max_connections} is below serve.max_pending="
                f"{self.max_pending}: the queue could never be filled (a query holds its "
                "connection until it is answered)"
            )

    @classmethod
    def from_config(cls, serve: Any) -> ServeSettings:
        """The settings of a composed config's `serve` node."""
        if not serve.model:
            raise ConfigError(
                "serve.model is not set: pass serve.model=FILE (a model.relocfw from a run)"
            )
        token = serve.token_file
        return cls(
            model=Path(str(serve.model)).expanduser(),
            host=str(serve.host),
            port=serve.port,
            workers=serve.workers,
            max_pending=serve.max_pending,
            max_bytes=serve.max_bytes,
            max_pixels=serve.max_pixels,
            token_file=Path(str(token)).expanduser() if token else None,
            retry_after_s=serve.retry_after_s,
            header_timeout_s=serve.header_timeout_s,
            body_timeout_s=serve.body_timeout_s,
            shutdown_timeout_s=serve.shutdown_timeout_s,
            max_connections=serve.max_connections,
            max_connections_per_client=serve.max_connections_per_client,
        )
