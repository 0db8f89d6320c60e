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
from collections.abc import Callable, Iterator
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
        "serve.header_timeout_s=3",
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


def poll(ask: Callable[[], httpx.Response], status: int, seconds: float) -> httpx.Response:
    """`ask()` again until it is answered `status` (at most `seconds`): for a state
    the service reaches on its own time (connections accepted, bytes received)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            answered = ask()
            if answered.status_code == status:
                return answered
            seen = f"{answered.status_code} {answered.text[:200]}"
        except httpx.TransportError as error:
            seen = repr(error)
        if time.monotonic() > deadline:
            raise AssertionError(f"no {status} within {seconds} s; the last answer: {seen}")
        time.sleep(0.05)


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
        assert read_until_closed(connection, 15.0) == b""
    assert 2.5 < time.monotonic() - started < 10.0  # serve.header_timeout_s=3


def test_connections_over_the_cap_are_refused_503_naming_the_key(impatient):
    def health() -> httpx.Response:
        return httpx.get(f"{impatient.url}/v1/health", timeout=5)

    with open_sockets(impatient.url, b"", 6):
        # Once the six are accepted (within the 3 s they have to send their headers).
        refused = poll(health, 503, 2.5)
        assert "serve.max_connections=6" in refused.json()["error"]
        assert refused.headers["retry-after"] == "1"
        # The header timeout closes the six: the service answers again.
        poll(health, 200, 15.0)
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
    # The stalled body stays for the whole test.
    overrides = ["serve.max_pending=1", f"serve.max_bytes={max_bytes}", "serve.body_timeout_s=60"]
    announced = (
        b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
        + f"Content-Length: {max_bytes}\r\n\r\n".encode()
        + b"\x00" * (max_bytes - len(IMAGE) // 2)
    )
    with running(serve_command(model, *overrides), tmp_path) as server:
        with open_sockets(server.url, announced, 1):
            # Once the service has received the stalled body's bytes.
            refused = poll(lambda: post_image(server.url), 503, 15.0)
            assert "serve.max_pending x serve.max_bytes" in refused.json()["error"]
            assert refused.headers["retry-after"] == "1"
            # Its body was not read to its end: the connection cannot carry another.
            assert refused.headers["connection"] == "close"
        # Once the service has seen the stalled client go: its bytes are given back.
        poll(lambda: post_image(server.url), 200, 15.0)


def test_a_body_that_timed_out_gives_its_bytes_back(model, tmp_path):
    """A stalled body answered 408 holds nothing after: a body that needs the whole
    budget (serve.max_pending x serve.max_bytes) is answered next."""
    max_bytes = 2 * len(IMAGE)
    overrides = ["serve.max_pending=1", f"serve.max_bytes={max_bytes}", "serve.body_timeout_s=1"]
    announced = (
        b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
        + f"Content-Length: {max_bytes}\r\n\r\n".encode()
        + b"\x00" * (max_bytes - len(IMAGE) // 2)
    )
    with running(serve_command(model, *overrides), tmp_path) as server:
        with open_sockets(server.url, announced, 1) as (connection,):
            received = read_until_closed(connection, 15.0)
        assert received.startswith(b"HTTP/1.1 408 "), received
        assert httpx.get(f"{server.url}/v1/health", timeout=5).json()["pending"] == 0
        answered = post_image(server.url)
        assert answered.status_code == 200, answered.text


FLOOD = 1100
# The flood's sockets, and the test process's other files (pytest, httpx, the model).
FLOOD_OPEN_FILES = FLOOD + 200
SERVICE_OPEN_FILES = 1024


@pytest.fixture
def open_files_for_a_flood() -> Iterator[None]:
    """This process may open the flood's sockets (its soft `ulimit -n` raised for the
    test, put back after), and the service's limit may be set to 1024; else skipped."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    unlimited = resource.RLIM_INFINITY
    if hard != unlimited and hard < max(FLOOD_OPEN_FILES, SERVICE_OPEN_FILES):
        pytest.skip(f"needs an open-file limit of {FLOOD_OPEN_FILES}; the hard limit is {hard}")
    if soft != unlimited and soft < FLOOD_OPEN_FILES:
        resource.setrlimit(resource.RLIMIT_NOFILE, (FLOOD_OPEN_FILES, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_a_flood_of_header_less_connections_neither_stops_the_service_nor_its_log(
    model, tmp_path, open_files_for_a_flood
):
    """The review's case: 1100 connections that send nothing, at `ulimit -n 1024`."""
    import resource

    def open_files_1024() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (SERVICE_OPEN_FILES, SERVICE_OPEN_FILES))

    service = start_server(serve_command(model), tmp_path, preexec_fn=open_files_1024)
    sockets = []
    try:
        for _ in range(FLOOD):  # all at once: connect without waiting for each
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
    # A Content-Length of its own: the module's service logs other tests' clients too.
    announced = SILENT_BODY.replace(b"Content-Length: 100000", b"Content-Length: 100077")
    mine = "a client left before its body was in (40 of 100077 bytes)"
    before = len(server.log.read_text())
    with open_sockets(server.url, announced + b"\x89PNG" * 10, 1):
        time.sleep(0.3)
    deadline = time.monotonic() + 10
    while mine not in server.log.read_text()[before:] and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.2)  # anything the service would write after its line
    log = server.log.read_text()[before:]
    assert "Traceback" not in log and "ClientDisconnect" not in log, log[-3000:]
    assert len([line for line in log.splitlines() if "100077" in line]) == 1, log[-3000:]
    assert mine in log, log[-3000:]
    assert post_image(server.url).status_code == 200


def read_response(connection: socket.socket, seconds: float = 10.0) -> tuple[bytes, bytes]:
    """One response's head and body from a keep-alive connection (its Content-Length)."""
    connection.settimeout(seconds)
    received = b""
    while b"\r\n\r\n" not in received:
        chunk = connection.recv(65536)
        assert chunk, f"closed before a whole response: {received!r}"
        received += chunk
    head, _, body = received.partition(b"\r\n\r\n")
    length = next(
        int(line.split(b":", 1)[1])
        for line in head.split(b"\r\n")
        if line.lower().startswith(b"content-length:")
    )
    while len(body) < length:
        chunk = connection.recv(65536)
        assert chunk, f"closed before a whole response: {head + body!r}"
        body += chunk
    return head, body


def test_a_keep_alive_connection_idle_between_requests_is_kept(server):
    """The header timeout (5 s) counts from the connection's opening or its last
    answer, not from the opening only: three requests 2 s apart, 6 s in all."""
    with open_sockets(server.url, b"", 1) as (connection,):
        for _ in range(3):
            time.sleep(2.0)
            connection.sendall(HEALTH)
            head, body = read_response(connection)
            assert head.startswith(b"HTTP/1.1 200 "), head
            assert b'"status":"ready"' in body


def test_an_http_1_0_request_is_answered(server):
    """HTTP/1.0 (no Host, no keep-alive): answered, then the connection is closed."""
    with open_sockets(server.url, b"GET /v1/health HTTP/1.0\r\n\r\n", 1) as (connection,):
        received = read_until_closed(connection, 10.0)
    assert received.split(b"\r\n")[0].endswith(b" 200 OK"), received
    post = (
        b"POST /v1/localize HTTP/1.0\r\nContent-Type: image/png\r\n"
        + f"Content-Length: {len(IMAGE)}\r\n\r\n".encode()
        + IMAGE
    )
    with open_sockets(server.url, post, 1) as (connection,):
        received = read_until_closed(connection, 30.0)
    assert received.split(b"\r\n")[0].endswith(b" 200 OK"), received
    assert b'"position"' in received


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
