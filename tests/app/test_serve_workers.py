"""serve.workers=2: two processes, each with the model loaded once, answer as the
Python API does, several queries at a time."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from relocfw.client import Client
from relocfw.model.model_file import load_model
from tests.app.test_serve_helpers import pixels, running, serve_command, tiny_model


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
