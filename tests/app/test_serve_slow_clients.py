"""Slow and hostile clients against a real service process on 127.0.0.1, with raw
sockets: bodies that never come, headers that never end, more connections than the
cap, a client that leaves mid-body, and SIGTERM / Ctrl-C while they are open. The good
clients are answered within seconds, the bad ones get a JSON refusal or a closed
connection, the log gets one line per bad client, and a stop ends in bounded time
with exit 0. Every loop here is bounded in count and in time."""

from __future__ import annotations

import contextlib
import signal
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlparse

import httpx
import pytest

from tests.app.test_serve_helpers import (
    pixels,
    png_of,
    running,
    serve_command,
    start_server,
    tiny_model,
)
from tests.app.test_serve_helpers import stop as stop_service

IMAGE = png_of(pixels(1))
SILENT_BODY = (
    b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
    b"Content-Length: 100000\r\n\r\n"
)
HALF_HEADERS = b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Ty"
BAD_CLIENTS = 8


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def server(model, tmp_path_factory):
    """A service with today's defaults."""
    with running(serve_command(model), tmp_path_factory.mktemp("serve")) as found:
        yield found


@pytest.fixture(scope="module")
def impatient(model, tmp_path_factory):
    """A service with short body and header timeouts and a small connection cap."""
    overrides = [
        "serve.body_timeout_s=1",
        "serve.header_timeout_s=1",
        "serve.max_connections=6",
        "serve.max_pending=4",
    ]
    with running(serve_command(model, *overrides), tmp_path_factory.mktemp("serve")) as found:
        yield found


def address_of(url: str) -> tuple[str, int]:
    parsed = urlparse(url)
    assert parsed.hostname == "127.0.0.1"  # these tests talk to this machine only
    return parsed.hostname, parsed.port


@contextmanager
def open_sockets(url: str, sent: bytes, count: int) -> Iterator[list[socket.socket]]:
    """`count` connections that each send `sent` and then nothing, closed at the end."""
    sockets = []
    try:
        for _ in range(count):
            connection = socket.create_connection(address_of(url), timeout=5)
            if sent:
                connection.sendall(sent)
            sockets.append(connection)
        yield sockets
    finally:
        for connection in sockets:
            connection.close()


def bad_clients(url: str) -> contextlib.ExitStack:
    """8 silent bodies (headers, Content-Length: 100000, no byte of it), 4 connections
    that send nothing and 4 that stop in the middle of their headers."""
    stack = contextlib.ExitStack()
    stack.enter_context(open_sockets(url, SILENT_BODY, BAD_CLIENTS))
    stack.enter_context(open_sockets(url, b"", BAD_CLIENTS // 2))
    stack.enter_context(open_sockets(url, HALF_HEADERS, BAD_CLIENTS // 2))
    return stack


def post_image(url: str, timeout: float = 10.0) -> httpx.Response:
    return httpx.post(
        f"{url}/v1/localize",
        content=IMAGE,
        headers={"Content-Type": "image/png"},
        timeout=timeout,
    )


def read_until_closed(connection: socket.socket, seconds: float) -> bytes:
    """What the server sends until it closes the connection (at most `seconds`)."""
    connection.settimeout(seconds)
    received = b""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        chunk = connection.recv(65536)
        if not chunk:
            return received
        received += chunk
    raise AssertionError(f"the connection was still open after {seconds} s: {received!r}")


def test_silent_bodies_and_unfinished_headers_do_not_stop_good_requests(server):
    with bad_clients(server.url):
        time.sleep(0.5)  # the server has read every bad client's headers by now
        started = time.monotonic()
        answered = post_image(server.url)
        seconds = time.monotonic() - started
        assert answered.status_code == 200, answered.text
        assert seconds < 5.0
        health = httpx.get(f"{server.url}/v1/health", timeout=5)
        assert health.status_code == 200 and health.json()["pending"] == 0


def test_a_silent_body_is_answered_408_naming_the_key_and_closed(impatient):
    with open_sockets(impatient.url, SILENT_BODY, 1) as (connection,):
        received = read_until_closed(connection, 10.0)
    head, _, body = received.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 "), received
    assert b"connection: close" in head.lower()
    assert b'{"error":"' in body and b"serve.body_timeout_s=1" in body


def test_a_connection_that_never_ends_its_headers_is_closed(impatient):
    with open_sockets(impatient.url, HALF_HEADERS, 1) as (connection,):
        started = time.monotonic()
        assert read_until_closed(connection, 10.0) == b""
    assert time.monotonic() - started < 5.0


def test_connections_over_the_cap_are_refused_503_naming_the_key(impatient):
    with open_sockets(impatient.url, b"", 6):
        time.sleep(0.3)  # accepted: six connections are open
        refused = httpx.get(f"{impatient.url}/v1/health", timeout=5)
        assert refused.status_code == 503
        assert "serve.max_connections=6" in refused.json()["error"]
        assert refused.headers["retry-after"] == "1"
        # The header timeout closes the six: the service answers again.
        time.sleep(2.0)
        assert httpx.get(f"{impatient.url}/v1/health", timeout=5).status_code == 200
    assert post_image(impatient.url).status_code == 200


def connection_from(url: str, source: str) -> socket.socket:
    """A connection to the service from the local address `source` (Linux routes all
    of 127.0.0.0/8 to the loopback: 127.0.0.2 is a second client on this machine)."""
    return socket.create_connection(address_of(url), timeout=5, source_address=(source, 0))


HEALTH = b"GET /v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"


def test_one_client_address_cannot_hold_every_connection(model, tmp_path):
    """The review's lock: one client held every connection the service serves. Now
    one address holds at most serve.max_connections_per_client of them; its next is
    refused 503 naming the key, while another address is still answered."""
    overrides = [
        "serve.max_connections=6",
        "serve.max_pending=4",
        "serve.max_connections_per_client=4",
        "serve.header_timeout_s=30",  # the held connections stay for the whole test
    ]
    with (
        running(serve_command(model, *overrides), tmp_path) as service,
        # 12 from 127.0.0.1, twice the service's cap: 4 served, the rest refused.
        open_sockets(service.url, b"", 12),
    ):
        with connection_from(service.url, "127.0.0.1") as extra:
            extra.sendall(HEALTH)
            head, _, body = read_until_closed(extra, 10.0).partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503 "), head
        assert b"serve.max_connections_per_client=4" in body, body
        assert b"retry-after: 1" in head.lower()
        other = httpx.HTTPTransport(local_address="127.0.0.2")
        with httpx.Client(base_url=service.url, transport=other, timeout=10) as client:
            assert client.get("/v1/health").status_code == 200
            answered = client.post(
                "/v1/localize", content=IMAGE, headers={"Content-Type": "image/png"}
            )
            assert answered.status_code == 200, answered.text


def test_bodies_arriving_at_once_are_bounded_by_the_bytes_received(model, tmp_path):
    """max_pending x max_bytes bounds the bodies still arriving: a client that sent
    most of a large body and stalls leaves too little for a good one (503 naming the
    keys); once it is gone, the good one is answered."""
    max_bytes = 2 * len(IMAGE)
    overrides = ["serve.max_pending=1", f"serve.max_bytes={max_bytes}"]
    announced = (
        b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
        + f"Content-Length: {max_bytes}\r\n\r\n".encode()
        + b"\x00" * (max_bytes - len(IMAGE) // 2)
    )
    with running(serve_command(model, *overrides), tmp_path) as server:
        with open_sockets(server.url, announced, 1):
            time.sleep(0.5)  # the server has received the stalled body's bytes by now
            refused = post_image(server.url)
            assert refused.status_code == 503, refused.text
            assert "serve.max_pending x serve.max_bytes" in refused.json()["error"]
            assert refused.headers["retry-after"] == "1"
        time.sleep(0.5)  # the stalled client has gone: its bytes are given back
        assert post_image(server.url).status_code == 200


def test_a_flood_of_header_less_connections_neither_stops_the_service_nor_its_log(model, tmp_path):
    """The review's case: 1100 connections that send nothing, at `ulimit -n 1024`."""
    import resource

    def open_files_1024() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))

    service = start_server(serve_command(model), tmp_path, preexec_fn=open_files_1024)
    sockets = []
    try:
        for _ in range(1100):  # all at once: connect without waiting for each
            connection = socket.socket()
            connection.setblocking(False)
            connection.connect_ex(address_of(service.url))
            sockets.append(connection)
        time.sleep(1.0)
        # The header timeout closes them as they come (the kernel retries the ones
        # not yet accepted); the service answers again within seconds.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(f"{service.url}/v1/health", timeout=5).status_code == 200:
                    break
            time.sleep(0.5)
        assert post_image(service.url).status_code == 200
    finally:
        for connection in sockets:
            connection.close()
        stop_service(service.process)
        service.process.stdout.close()
    log = service.log.read_text()
    assert "Too many open files" not in log, log[-3000:]
    assert len(log.splitlines()) < 20, log[-3000:]


def test_a_client_that_leaves_mid_body_is_one_line_in_the_log(server):
    before = len(server.log.read_text())
    with open_sockets(server.url, SILENT_BODY + b"\x89PNG" * 10, 1):
        time.sleep(0.3)
    deadline = time.monotonic() + 10
    while "left" not in server.log.read_text()[before:] and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.2)  # anything the service would write after its line
    log = server.log.read_text()[before:]
    assert "Traceback" not in log and "ClientDisconnect" not in log, log[-3000:]
    lines = [line for line in log.splitlines() if line.strip()]
    assert len(lines) == 1, log[-3000:]
    assert "a client left before its body was in (40 of 100000 bytes)" in lines[0]
    assert post_image(server.url).status_code == 200


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_a_stop_with_bad_clients_open_exits_0_in_bounded_time(model, tmp_path, stop):
    command = serve_command(model, "serve.shutdown_timeout_s=2")
    with running(command, tmp_path) as service, bad_clients(service.url):
        time.sleep(0.5)
        assert post_image(service.url).status_code == 200
        started = time.monotonic()
        service.process.send_signal(stop)
        try:
            status = service.process.wait(timeout=15)
        except Exception as error:
            raise AssertionError(f"still running 15 s after {stop.name}") from error
        seconds = time.monotonic() - started
    log = service.log.read_text()
    assert status == 0, log[-3000:]
    assert seconds < 8.0
    assert "stopped" in log and "interrupted" not in log
    assert "Traceback" not in log, log[-3000:]
