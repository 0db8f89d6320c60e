"""The serve.* options (conf/config.yaml), checked once before anything is loaded."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from relocfw.core.errors import ConfigError

# A bound on decoded pixels, below imaging.MAX_IMAGE_PIXELS (2^30, 3 GiB as RGB): a
# 20 MB PNG may announce 30000 x 30000 pixels, and a service decodes many requests
# at once. 50 MP is well above any robot camera.
DEFAULT_MAX_PIXELS = 50_000_000


def whole_number(key: str, value: Any, least: int, most: int | None = None) -> int:
    """`value` as an int in [least, most], or a ConfigError naming serve.KEY."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"serve.{key} must be a whole number, got {value!r}")
    if value < least or (most is not None and value > most):
        bound = f">= {least}" if most is None else f"in [{least}, {most}]"
        raise ConfigError(f"serve.{key} must be {bound}, got {value}")
    return value


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

    def __post_init__(self) -> None:
        if not str(self.host).strip():
            raise ConfigError("serve.host is empty: pass an address, e.g. serve.host=127.0.0.1")
        whole_number("port", self.port, 0, 65535)
        whole_number("workers", self.workers, 1)
        whole_number("max_pending", self.max_pending, 1)
        whole_number("max_bytes", self.max_bytes, 1)
        whole_number("max_pixels", self.max_pixels, 1)
        whole_number("retry_after_s", self.retry_after_s, 0)
        if self.max_pending < self.workers:
            raise ConfigError(
                f"serve.max_pending={self.max_pending} is below serve.workers="
                f"{self.workers}: some workers could never be given a query"
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
        )
