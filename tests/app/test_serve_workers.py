"""serve.workers=2: two processes, each with the model loaded once, answer as the
Python API does, several queries at a time."""

from __future__ import annotations

import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from relocfw.client import Client
from relocfw.model.model_file import load_model
from tests.app.test_serve_helpers import (
    pixels,
    png_of,
    running,
    serve_command,
    start_server,
    stop,
    tiny_model,
    wait_for,
)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def server(model, tmp_path_factory):
    command = serve_command(model, "serve.workers=2", "serve.max_pending=4")
    with running(command, tmp_path_factory.mktemp("serve")) as found:
        yield found


def test_two_worker_processes_answer_as_the_python_api(server, model):
    images = [pixels(seed) for seed in range(20, 26)]

    def ask(image):
        with Client(server.url) as client:
            return client.localize(image)

    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(ask, images))
    reference = load_model(model)
    for image, answer in zip(images, answers, strict=True):
        expected = reference.localize(image)
        assert np.allclose(answer.position, expected.pose.position, rtol=0, atol=1e-6)
        assert np.allclose(answer.quaternion, expected.pose.quaternion, rtol=0, atol=1e-6)
    with Client(server.url) as client:
        health = client.health()
    assert (health["workers"], health["answered"], health["pending"]) == (2, 6, 0)


def test_ctrl_c_to_the_whole_process_group_drains_the_workers(model, tmp_path):
    """A terminal's Ctrl-C signals the whole process group (systemd's stop sends
    SIGTERM the same way, and the workers ignore both alike): the worker processes
    get the signal too. The queries in flight are still answered (no 500), the log
    holds no traceback, and the service exits 0 in bounded time."""
    signum = signal.SIGINT
    image = png_of(pixels(3))
    command = serve_command(model, "serve.workers=2", "serve.max_pending=4")
    service = start_server(command, tmp_path)  # its own session: its pid is the group's id
    codes: list[int] = []
    done = threading.Event()

    def ask() -> None:
        with httpx.Client(base_url=service.url, timeout=20) as client:
            while not done.is_set():
                try:
                    answered = client.post(
                        "/v1/localize", content=image, headers={"Content-Type": "image/png"}
                    )
                except httpx.TransportError:
                    return  # the service has stopped listening
                codes.append(answered.status_code)

    askers = [threading.Thread(target=ask) for _ in range(3)]
    try:
        for asker in askers:
            asker.start()
        wait_for(lambda: len(codes) >= 6, 60.0, "six answers")
        started = time.monotonic()
        os.killpg(service.process.pid, signum)
        try:
            status = service.process.wait(timeout=30)
        except Exception as error:
            raise AssertionError(f"still running 30 s after {signum.name}") from error
        seconds = time.monotonic() - started
    finally:
        done.set()
        for asker in askers:
            asker.join(timeout=30)
        stop(service.process)
        service.process.stdout.close()
    log = service.log.read_text()
    assert status == 0, log[-3000:]
    assert set(codes) <= {200, 503}, (sorted(set(codes)), log[-3000:])
    assert "Traceback" not in log, log[-3000:]
    assert seconds < 15.0


def worker_processes(server_pid: int) -> list[int]:
    """The pids of a service's worker processes (its spawned children)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                parent = int(stat.read().rpartition(")")[2].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as cmdline:
                spawned = b"spawn_main" in cmdline.read()
        except (OSError, ValueError, IndexError):
            continue  # ended meanwhile
        if parent == server_pid and spawned:
            found.append(int(entry))
    return found


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="finds the workers through /proc")
def test_a_killed_worker_process_is_a_json_503_not_a_500(model, tmp_path):
    """A worker killed from outside (the OOM killer, kill -9) breaks its pool: each
    query is then refused 503 in one JSON line, and the log has no traceback."""
    command = serve_command(model, "serve.workers=2", "serve.max_pending=4")
    with running(command, tmp_path) as service:
        workers = worker_processes(service.process.pid)
        assert len(workers) == 2, workers
        os.kill(workers[0], signal.SIGKILL)
        time.sleep(0.5)  # the pool notices its worker is gone
        for _ in range(2):
            refused = httpx.post(
                f"{service.url}/v1/localize",
                content=png_of(pixels(4)),
                headers={"Content-Type": "image/png"},
                timeout=20,
            )
            assert refused.status_code == 503, refused.text
            assert "a worker process of the service has ended" in refused.json()["error"]
        assert httpx.get(f"{service.url}/v1/health", timeout=5).json()["pending"] == 0
    log = service.log.read_text()
    assert "Traceback" not in log, log[-3000:]
