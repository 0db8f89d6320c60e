"""A small typed client of `relocfw serve` (docs/serve.md), over httpx.

    >>> from relocfw.client import Client  # doctest: +SKIP
    >>> with Client("http://127.0.0.1:8000") as client:  # doctest: +SKIP
    ...     answer = client.localize("frame.png")
    ...     answer.position, answer.quaternion  # camera-to-world; w, x, y, z

A refusal (4xx, 5xx) raises ServiceError with the service's one-line message; a 503
carries the seconds the service asked to wait (`retry_after`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ServiceError(Exception):
    """The service refused a request: its status, its message and, for a 503, the
    Retry-After seconds (None when not given)."""

    def __init__(self, status: int, message: str, retry_after: float | None = None) -> None:
        super().__init__(f"{status}: {message}")
        self.status = status
        self.message = message
        self.retry_after = retry_after


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera's intrinsics, in pixels of the image sent."""

    fx: float
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class ErrorBounds:
    """Calibrated bounds: the answer's errors stay below these for `coverage` of answers
    like it; None where unbounded."""

    position: float | None
    orientation_deg: float | None
    coverage: float | None


@dataclass(frozen=True)
class Answer:
    """POST /v1/localize's answer (docs/serve.md lists the fields)."""

    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]  # w, x, y, z: camera-to-world
    units: str
    confidence: float | None
    error_bounds: ErrorBounds | None
    fell_back: bool
    uncertainty_name: str
    uncertainty_value: float | None
    ms: Mapping[str, float]
    model_id: str
    raw: Mapping[str, Any] = field(repr=False)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Answer:
        bounds = data.get("error_bounds")
        uncertainty = data.get("uncertainty") or {}
        return cls(
            position=tuple(float(v) for v in data["position"]),  # type: ignore[arg-type]
            quaternion=tuple(float(v) for v in data["quaternion"]),  # type: ignore[arg-type]
            units=str(data["units"]),
            confidence=data.get("confidence"),
            error_bounds=None if bounds is None else ErrorBounds(**bounds),
            fell_back=bool(data["fell_back"]),
            uncertainty_name=str(uncertainty.get("name", "none")),
            uncertainty_value=uncertainty.get("value"),
            ms=dict(data["ms"]),
            model_id=str(data["model_id"]),
            raw=dict(data),
        )


def encoded(image: bytes | str | Path | np.ndarray) -> tuple[bytes, str]:
    """(body, content type) of an encoded image's bytes, an image file (read here,
    on the caller's side), or H x W x 3 uint8 RGB pixels (sent as PNG: lossless, so
    the service localizes exactly these pixels)."""
    if isinstance(image, np.ndarray):
        import cv2

        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"pixels must be H x W x 3 uint8 RGB, got {image.dtype} {image.shape}")
        ok, data = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
        if not ok:
            raise ValueError("OpenCV could not encode the pixels as PNG")
        return data.tobytes(), "image/png"
    body = Path(image).read_bytes() if isinstance(image, str | Path) else bytes(image)
    return body, "image/png" if body.startswith(PNG_SIGNATURE) else "image/jpeg"


def checked(response: httpx.Response) -> Any:
    """The JSON of a 2xx answer; ServiceError for anything else."""
    if response.is_success:
        return response.json()
    try:
        message = str(response.json().get("error", response.text))
    except ValueError:
        message = response.text or response.reason_phrase
    retry = response.headers.get("retry-after")
    seconds = float(retry) if retry and retry.replace(".", "", 1).isdigit() else None
    raise ServiceError(response.status_code, message, seconds)


class Client:
    """A connection to one service; close it (or use `with`) when done.

    Args:
        url: the service's base URL, as `relocfw serve` prints it.
        token: the bearer token when the service has a serve.token_file.
        timeout: seconds to wait for an answer (a queued query waits its turn).
    """

    def __init__(
        self, url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 60.0
    ) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url, headers=headers, timeout=timeout)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def health(self) -> dict[str, Any]:
        return checked(self.http.get("/v1/health"))

    def model(self) -> dict[str, Any]:
        return checked(self.http.get("/v1/model"))

    def localize(
        self,
        image: bytes | str | Path | np.ndarray,
        camera: Intrinsics | None = None,
        name: str | None = None,
    ) -> Answer:
        """The camera-to-world pose of one image.

        Raises:
            ServiceError: the service refused it (its status and message).
            ValueError: intrinsics that are not finite numbers, or pixels that are
                not H x W x 3 uint8.
        """
        body, content_type = encoded(image)
        params: dict[str, str] = {}
        if camera is not None:
            for key in ("fx", "fy", "cx", "cy"):
                value = float(getattr(camera, key))
                if not math.isfinite(value):
                    raise ValueError(f"camera {key} must be finite, got {value}")
                params[key] = repr(value)
        if name is not None:
            params["name"] = name
        response = self.http.post(
            "/v1/localize", content=body, params=params, headers={"Content-Type": content_type}
        )
        return Answer.from_json(checked(response))
