"""The FastAPI application: three endpoints over a loaded model's queue.

Every refusal is one JSON object {"error": "one line"} with a 4xx status, raised
before any work it would waste: the token (401), the content type (415), the query
fields (422), the body's size (413) and its time (408), a full queue (503) and the
image (400). The service goes on serving after each. A request takes its queue place
only once its whole body is in, so clients that send their bodies slowly, or never,
hold no place a real query needs (the body timeout ends them); the bodies still
arriving are bounded by the bytes received (relocfw.serve.body_budget, 503).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import FastAPI, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import MAX_ASPECT
from relocfw.core.version import VERSION
from relocfw.serve.answers import ModelInfo, Timings, answer_json
from relocfw.serve.auth import BearerToken
from relocfw.serve.body_budget import BodyBudget, BodyBudgetError
from relocfw.serve.fields import FieldError, parse_fields
from relocfw.serve.guard import CLIENT_LEFT, LOG, ASGIApp, Guarded, over_capacity, refusal
from relocfw.serve.images import MediaTypeError, check_content_type, decode_image
from relocfw.serve.queue import QueryQueue, QueueFullError, WorkersLostError
from relocfw.serve.settings import ServeSettings
from relocfw.serve.workers import Query as LocalizeQuery

IMAGE_BODY = {"schema": {"type": "string", "format": "binary"}}
LOCALIZE_BODY = {
    "requestBody": {
        "required": True,
        "description": "the encoded image, PNG or JPEG",
        "content": {"image/png": IMAGE_BODY, "image/jpeg": IMAGE_BODY},
    }
}


class BodyTooLargeError(DataError):
    """The body is over serve.max_bytes (answered 413)."""


class BodyTimeoutError(DataError):
    """The body was not in within serve.body_timeout_s (answered 408)."""


class UnauthorizedError(DataError):
    """No token, or not the one in serve.token_file (answered 401)."""


class ClientLeftError(Exception):
    """The client disconnected before its whole body was in."""

    def __init__(self, received: int, declared: str) -> None:
        super().__init__(f"{received} of {declared or 'unknown'} bytes")


@dataclass(frozen=True)
class Service:
    """What the application serves."""

    settings: ServeSettings
    queue: QueryQueue
    info: ModelInfo
    token: BearerToken | None = None
    # The loaded model's query.max_aspect: a body's header is held to it before decoding.
    max_aspect: float = MAX_ASPECT


def status_of(error: Exception) -> int:
    """The 4xx of one of relocfw's refusals."""
    for kind, status in (
        (UnauthorizedError, 401),
        (BodyTooLargeError, 413),
        (BodyTimeoutError, 408),
        (MediaTypeError, 415),
        (FieldError, 422),
        (ConfigError, 422),
    ):
        if isinstance(error, kind):
            return status
    return 400


async def read_body(request: Request, max_bytes: int, budget: BodyBudget) -> bytes:
    """The body, refused (BodyTooLargeError) as soon as it is known to pass `max_bytes`:
    from Content-Length before reading, else while reading, never held whole. Its bytes
    are held in `budget` while they arrive and given back when it is in or dropped.

    Raises:
        ClientLeftError: the client disconnected before the body's end.
        BodyBudgetError: the bodies arriving at once would pass the budget.
    """
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > max_bytes:
        raise BodyTooLargeError(f"the body is {declared} bytes, over serve.max_bytes={max_bytes}")
    chunks, size = [], 0
    try:
        async for chunk in request.stream():
            if size + len(chunk) > max_bytes:
                raise BodyTooLargeError(f"the body is over serve.max_bytes={max_bytes} bytes")
            budget.take(len(chunk))
            size += len(chunk)
            chunks.append(chunk)
    except ClientDisconnect:
        raise ClientLeftError(size, declared) from None
    finally:
        budget.give_back(size)
    return b"".join(chunks)


async def read_body_in_time(request: Request, settings: ServeSettings, budget: BodyBudget) -> bytes:
    """read_body within serve.body_timeout_s (BodyTimeoutError after it): a deadline
    for the whole body, not for each chunk, so a client cannot hold its connection by
    trickling bytes."""
    try:
        # wait_for, not asyncio.timeout (Python 3.11); on 3.10 it raises
        # asyncio.TimeoutError, which is not yet the builtin TimeoutError.
        return await asyncio.wait_for(
            read_body(request, settings.max_bytes, budget), settings.body_timeout_s
        )
    except asyncio.TimeoutError:
        raise BodyTimeoutError(
            f"the body was not in within serve.body_timeout_s={settings.body_timeout_s:g} "
            "seconds of the request's headers"
        ) from None


async def client_left(request: Request) -> None:
    """Returns when the client disconnects (the body is read by then: the next
    message the server gives is the disconnect)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


def served_app(service: Service) -> ASGIApp:
    """What uvicorn runs: the application, its refusals counted (relocfw.serve.guard)."""
    settings = service.settings
    return Guarded(create_app(service), service.queue.counts, settings.shutdown_timeout_s)


def over_capacity_app(service: Service, key: str) -> ASGIApp:
    """What a connection above serve.KEY (max_connections or max_connections_per_client)
    runs: a JSON 503 naming the key, counted."""
    settings = service.settings
    whose = "the service has" if key == "max_connections" else "this client address has"
    message = (
        f"{whose} serve.{key}={getattr(settings, key)} connections open; retry after the "
        "Retry-After seconds"
    )
    refuse = over_capacity(message, settings.retry_after_s)
    return Guarded(refuse, service.queue.counts, settings.shutdown_timeout_s)


def create_app(service: Service) -> FastAPI:
    """The application; its lifespan's end waits for the workers' queries to finish.

    With a token (serve.token_file) the schema needs it too and FastAPI's pages (/docs,
    /redoc) are off: a browser cannot send the token to them.
    """

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        yield
        await run_in_threadpool(service.queue.workers.shutdown)

    # The bodies still arriving, bounded as the queue's places bound the bodies in.
    bodies = BodyBudget(service.settings.max_pending * service.settings.max_bytes)
    pages: dict[str, Any] = (
        {"docs_url": None, "redoc_url": None, "openapi_url": None} if service.token else {}
    )
    app = FastAPI(
        title="relocfw",
        version=VERSION,
        summary="6-DoF camera pose of one image against a loaded map",
        lifespan=lifespan,
        **pages,
    )

    @app.exception_handler(DataError)
    @app.exception_handler(ConfigError)
    async def refused(_: Request, error: Exception) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if isinstance(error, UnauthorizedError) else None
        # The body was not read to its end: the connection cannot carry another request.
        unread = isinstance(error, BodyTimeoutError | BodyTooLargeError)
        return refusal(status_of(error), str(error), headers, close=unread)

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, error: RequestValidationError) -> JSONResponse:
        first = error.errors()[0]
        where = ".".join(str(part) for part in first.get("loc", ()))
        return refusal(422, f"{where}: {first.get('msg', 'invalid')}")

    @app.exception_handler(HTTPException)
    async def http_error(_: Request, error: HTTPException) -> JSONResponse:
        return refusal(error.status_code, str(error.detail), error.headers)

    def has_token(request: Request) -> bool:
        return service.token is None or service.token.allows(request.headers.get("authorization"))

    def check_token(request: Request) -> None:
        if not has_token(request):
            raise UnauthorizedError(
                "this service needs a bearer token: send `Authorization: Bearer TOKEN` "
                "with the token of its serve.token_file"
            )

    if service.token is not None:

        @app.get("/openapi.json", include_in_schema=False)
        async def schema(request: Request) -> dict[str, Any]:
            check_token(request)
            return app.openapi()

    @app.get(
        "/v1/health",
        summary="Ready, and how full the queue is (with a token set, callers without it "
        "get the status only)",
    )
    async def health(request: Request) -> dict[str, Any]:
        if not has_token(request):
            return {"status": "ready"}
        counts = service.queue.counts
        return {
            "status": "ready",
            "model_id": service.info.model_id,
            "workers": service.settings.workers,
            "pending": counts.pending,
            "max_pending": service.settings.max_pending,
            "answered": counts.answered,
            "refused": counts.refused,
            "abandoned": counts.abandoned,
        }

    @app.get("/v1/model", summary="What the service runs")
    async def model(request: Request) -> dict[str, Any]:
        check_token(request)
        return service.info.as_json()

    @app.post(
        "/v1/localize",
        summary="Camera-to-world pose of one image",
        openapi_extra=LOCALIZE_BODY,
    )
    async def localize(
        request: Request,
        fx: Annotated[float | None, Query(description="focal length x, pixels")] = None,
        fy: Annotated[float | None, Query(description="focal length y, pixels")] = None,
        cx: Annotated[float | None, Query(description="principal point x, pixels")] = None,
        cy: Annotated[float | None, Query(description="principal point y, pixels")] = None,
        name: Annotated[str | None, Query(description="frame name, for refine=sequence")] = None,
    ) -> Response:
        # The typed parameters document the fields; the query string is read by
        # parse_fields, which refuses unknown and repeated fields too.
        started = time.perf_counter()
        check_token(request)
        check_content_type(request.headers.get("content-type"))
        fields = parse_fields(request.query_params.multi_items())
        queue = service.queue
        retry = {"Retry-After": str(service.settings.retry_after_s)}
        full = (
            f"the service is busy: {queue.max_pending} queries are waiting or running "
            "(serve.max_pending); retry after the Retry-After seconds"
        )
        try:
            body = await read_body_in_time(request, service.settings, bodies)
        except BodyBudgetError as error:
            # The body was not read to its end: the connection cannot carry another.
            return refusal(503, str(error), retry, close=True)
        except ClientLeftError as left:
            LOG.warning("relocfw serve: a client left before its body was in (%s)", left)
            return Response(status_code=CLIENT_LEFT)
        try:
            queue.reserve()  # once the body is in: the decoded images count too
        except QueueFullError:
            return refusal(503, full, retry)
        handed_over = False
        try:
            image = await run_in_threadpool(
                decode_image, body, service.settings.max_pixels, service.max_aspect
            )
            camera = fields.camera(image.shape[1], image.shape[0])
            decoded = time.perf_counter()
            handed_over = True
            answer = await queue.run(
                LocalizeQuery(image, camera, fields.name), client_left(request)
            )
        except WorkersLostError as error:
            LOG.error("relocfw serve: %s", error)
            return refusal(503, str(error))
        finally:
            if not handed_over:
                queue.release()
        if answer is None:
            return Response(status_code=CLIENT_LEFT)
        finished = time.perf_counter()
        timings = Timings(
            decode_ms=1000.0 * (decoded - started),
            queue_ms=1000.0 * (finished - decoded),
            total_ms=1000.0 * (finished - started),
        )
        return JSONResponse(answer_json(answer, service.info, timings, fields.name))

    return app
