"""The queue, a client that leaves, and SIGTERM, on a service whose queries wait at a
gate the test opens (tests/app/test_serve_helpers.py): a query is held in flight for
exactly as long as a test needs, so none of these depends on timing."""

from __future__ import annotations

import signal
import socket
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlparse

import httpx
import pytest

from relocfw.client import Client, ServiceError
from tests.app.test_serve_helpers import (
    gated_command,
    pixels,
    png_of,
    running,
    tiny_model,
    wait_for,
)

IMAGE = png_of(pixels(1))


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def gate(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("gate")


@pytest.fixture(scope="module")
def server(model, gate, tmp_path_factory):
    command = gated_command(model, gate, "serve.max_pending=2", "serve.retry_after_s=3")
    with running(command, tmp_path_factory.mktemp("serve")) as found:
        yield found


@pytest.fixture
def closed(gate):
    """The gate shut, with no query started yet; opened again after the test, so a
    failing test leaves no query waiting."""
    for path in gate.iterdir():
        path.unlink()
    yield gate
    (gate / "open").touch()


def started(gate: Path) -> int:
    return len(list(gate.glob("started-*")))


def health(server) -> dict:
    return httpx.get(f"{server.url}/v1/health", timeout=10).json()


def localize(url: str):
    with Client(url) as client:
        return client.localize(IMAGE)


def test_a_full_queue_answers_503_with_retry_after_then_serves_again(server, closed):
    with ThreadPoolExecutor(2) as pool:
        running_query = pool.submit(localize, server.url)
        wait_for(lambda: started(closed) == 1, what="the first query to run")
        waiting_query = pool.submit(localize, server.url)
        wait_for(lambda: health(server)["pending"] == 2, what="the second query to wait")
        with Client(server.url) as client, pytest.raises(ServiceError) as refused:
            client.localize(IMAGE)
        assert refused.value.status == 503
        assert refused.value.retry_after == 3.0
        assert "serve.max_pending" in refused.value.message
        (closed / "open").touch()
        first, second = running_query.result(timeout=30), waiting_query.result(timeout=30)
    assert first.position == second.position
    assert health(server)["pending"] == 0
    assert localize(server.url).position == first.position


def test_a_client_that_leaves_while_waiting_costs_no_query(server, closed):
    before = health(server)
    with ThreadPoolExecutor(1) as pool:
        running_query = pool.submit(localize, server.url)
        wait_for(lambda: started(closed) == 1, what="the first query to run")
        # The client gives up waiting, and closes its connection.
        with (
            httpx.Client(base_url=server.url, timeout=0.5) as leaving,
            pytest.raises(httpx.ReadTimeout),
        ):
            leaving.post("/v1/localize", content=IMAGE, headers={"Content-Type": "image/png"})
        wait_for(
            lambda: health(server)["abandoned"] == before["abandoned"] + 1,
            what="the service to see the client leave",
        )
        assert health(server)["pending"] == 1  # the waiting query is gone from the queue
        (closed / "open").touch()
        running_query.result(timeout=30)
    wait_for(lambda: health(server)["pending"] == 0, what="the queue to empty")
    assert started(closed) == 1  # the abandoned query never ran


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "Ctrl-C"])
def test_a_stop_finishes_the_query_in_flight_then_exits_0(model, tmp_path, stop):
    gate = tmp_path / "gate"
    gate.mkdir()
    with running(gated_command(model, gate), tmp_path) as server:
        with ThreadPoolExecutor(1) as pool:
            in_flight = pool.submit(localize, server.url)
            wait_for(lambda: started(gate) == 1, what="the query to run")
            server.process.send_signal(stop)
            address = urlparse(server.url)

            def refuses_connections() -> bool:
                try:
                    socket.create_connection((address.hostname, address.port), 1).close()
                except OSError:
                    return True
                return False

            wait_for(refuses_connections, what="the service to stop accepting")
            assert server.process.poll() is None  # still finishing the query
            (gate / "open").touch()
            answer = in_flight.result(timeout=30)
        assert len(answer.position) == 3
        assert server.process.wait(timeout=60) == 0
    log = server.log.read_text()
    assert "stopped" in log and "interrupted" not in log


def test_a_request_still_open_when_the_stop_times_out_is_answered_503(model, tmp_path):
    """serve.shutdown_timeout_s after a stop, a request still open (its query waits
    at the gate) is answered a JSON 503 and logged in one line; the query running in
    the worker is still finished, and the process exits 0."""
    gate = tmp_path / "gate"
    gate.mkdir()
    request = (
        b"POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
        + f"Content-Length: {len(IMAGE)}\r\n\r\n".encode()
        + IMAGE
    )
    command = gated_command(model, gate, "serve.shutdown_timeout_s=1")
    with running(command, tmp_path) as server:
        address = urlparse(server.url)
        with socket.create_connection((address.hostname, address.port), 10) as connection:
            connection.sendall(request)
            wait_for(lambda: started(gate) == 1, what="the query to run")
            server.process.send_signal(signal.SIGTERM)
            connection.settimeout(30)
            received = b""
            while chunk := connection.recv(65536):
                received += chunk
        (gate / "open").touch()  # the worker's query ends: the process can
        assert server.process.wait(timeout=60) == 0
    head, _, body = received.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503 "), received
    assert body == b'{"error":"the service is stopping"}'
    log = server.log.read_text()
    still_open = [line for line in log.splitlines() if "was still open" in line]
    assert len(still_open) == 1, log[-3000:]
    assert "serve.shutdown_timeout_s=1 s after the stop: answered 503" in still_open[0]
    assert "Traceback" not in log, log[-3000:]
