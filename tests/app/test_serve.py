"""relocfw serve, called over HTTP as a robot would: a real service process (tiny
model, free port) and real clients. Answers equal Relocalizer.localize's; every bad
request gets one 4xx line and the service goes on answering."""

from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
from hydra import compose, initialize_config_module

from relocfw.client import Client, Intrinsics, ServiceError
from relocfw.core.values import Localization
from relocfw.model.model_file import load_model
from tests.app.test_serve_helpers import (
    MAX_BYTES,
    MAX_PIXELS,
    jpeg_of,
    pixels,
    png_of,
    running,
    serve_command,
    tiny_model,
)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("model"))


@pytest.fixture(scope="module")
def server(model, tmp_path_factory):
    overrides = [f"serve.max_bytes={MAX_BYTES}", f"serve.max_pixels={MAX_PIXELS}"]
    with running(serve_command(model, *overrides), tmp_path_factory.mktemp("serve")) as found:
        yield found


@pytest.fixture(scope="module")
def reference(model):
    """The model as the Python API loads it: what every answer must equal."""
    return load_model(model)


def assert_same_answer(served: dict, expected: Localization) -> None:
    assert np.allclose(served["position"], expected.pose.position, rtol=0, atol=1e-6)
    assert np.allclose(served["quaternion"], expected.pose.quaternion, rtol=0, atol=1e-6)
    assert served["crop"] == {
        "x": expected.crop.x,
        "y": expected.crop.y,
        "size": expected.crop.size,
    }
    assert served["uncertainty"]["name"] == "spread"
    assert served["uncertainty"]["value"] == pytest.approx(expected.position_spread, abs=1e-6)


def post(client: httpx.Client, body: bytes, content_type="image/png", **params) -> httpx.Response:
    return client.post(
        "/v1/localize", content=body, params=params, headers={"Content-Type": content_type}
    )


def test_the_service_binds_this_machine_only_by_default(server):
    assert server.url.startswith("http://127.0.0.1:")
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        cfg = compose("config", overrides=["task=serve"])
    assert cfg.serve.host == "127.0.0.1"
    assert cfg.serve.token_file is None


def test_health_says_ready_and_how_full_the_queue_is(server):
    with server.client() as client:
        health = client.get("/v1/health").json()
    assert health["status"] == "ready"
    assert (health["pending"], health["workers"], health["max_pending"]) == (0, 1, 8)


def test_model_says_what_it_runs_and_names_the_file_by_its_hash(server, model):
    with Client(server.url) as client:
        found = client.model()
    assert found["model_id"] == hashlib.sha256(model.read_bytes()).hexdigest()[:16]
    assert (found["backbone"], found["crop_search"], found["refiner"]) == (
        "PoseNet",
        "SweepCrop",
        None,
    )
    assert (found["input_size"], found["units"], found["relocfw_version"]) == (32, "m", "0.1.0")
    assert found["uncertainty_signal"] == "spread"


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_answer_equals_relocalizer_localize_on_the_same_pixels(server, reference, seed):
    image = pixels(seed)
    with Client(server.url) as client:
        answer = client.localize(image, camera=Intrinsics(40.0, 41.0, 24.0, 18.0), name="seq/f1")
    assert_same_answer(dict(answer.raw), reference.localize(image))
    assert answer.quaternion == tuple(answer.raw["quaternion"])
    assert answer.raw["quaternion_order"] == "wxyz" and answer.raw["pose"] == "camera_to_world"
    assert answer.raw["name"] == "seq/f1" and answer.units == "m"
    assert answer.error_bounds is None  # the tiny model has no calibrated bounds
    assert answer.fell_back is False and answer.confidence is None
    assert set(answer.ms) >= {"decode", "queue", "localize", "total"}
    assert answer.ms["total"] >= answer.ms["localize"] > 0


def test_a_jpeg_is_answered_as_localize_answers_its_decoded_pixels(server, reference, tmp_path):
    import cv2

    data = jpeg_of(pixels(4))
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    with Client(server.url) as client:
        answer = client.localize(data)
    assert_same_answer(dict(answer.raw), reference.localize(np.ascontiguousarray(decoded)))


@pytest.mark.parametrize(
    "encode",
    [
        # 16-bit colour: OpenCV scales it to 8 bits (v * 257 >> 8 == v), as localize does.
        lambda image: png_of(image.astype(np.uint16) * 257),
        # 4 channels: the alpha is dropped, as localize does.
        lambda image: png_of(np.dstack([image, np.full(image.shape[:2], 90, np.uint8)])),
    ],
    ids=["16-bit colour", "rgba"],
)
def test_16_bit_and_4_channel_colour_are_converted_as_localize_converts_them(
    server, reference, encode
):
    image = pixels(5)
    with server.client() as client:
        response = post(client, encode(image))
    assert response.status_code == 200, response.text
    assert_same_answer(response.json(), reference.localize(image))


def announcing(width: int, height: int) -> bytes:
    """A PNG whose header announces width x height (the pixels are a 4 x 4 image's)."""
    data = bytearray(png_of(pixels(6, 4, 4)))
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    return bytes(data)


GOOD_PNG = png_of(pixels(7))
GOOD_JPEG = jpeg_of(pixels(7))

# (body, content type, query fields) -> (status, words of the one-line message)
BAD_REQUESTS = {
    "empty body": ((b"", "image/png", {}), (400, "empty")),
    "not an image": ((b"hello, I am text", "image/png", {}), (400, "not a PNG or JPEG")),
    "truncated jpeg": ((GOOD_JPEG[: len(GOOD_JPEG) // 2], "image/jpeg", {}), (400, "JPEG")),
    "jpeg without its end": ((GOOD_JPEG[:-2], "image/jpeg", {}), (400, "truncated JPEG")),
    "truncated png": ((GOOD_PNG[: len(GOOD_PNG) // 2], "image/png", {}), (400, "PNG")),
    "png header only": ((GOOD_PNG[:20], "image/png", {}), (400, "header")),
    "70000 x 70000": ((announcing(70000, 70000), "image/png", {}), (400, "70000 x 70000")),
    "over max_pixels": ((announcing(2000, 1000), "image/png", {}), (400, "serve.max_pixels")),
    "over max_bytes": (
        (GOOD_PNG + bytes(MAX_BYTES), "image/png", {}),
        (413, "serve.max_bytes"),
    ),
    "16-bit grey": ((png_of(np.full((8, 8), 4000, np.uint16)), "image/png", {}), (400, "16-bit")),
    "text content type": ((GOOD_PNG, "text/plain", {}), (415, "Content-Type")),
    "no content type": ((GOOD_PNG, "", {}), (415, "Content-Type")),
    "nan intrinsics": ((GOOD_PNG, "image/png", dict(fx="nan", fy=1, cx=1, cy=1)), (422, "fx")),
    "inf intrinsics": ((GOOD_PNG, "image/png", dict(fx=1, fy="inf", cx=1, cy=1)), (422, "fy")),
    "negative focal": ((GOOD_PNG, "image/png", dict(fx=-5, fy=5, cx=1, cy=1)), (422, "fx")),
    "not a number": ((GOOD_PNG, "image/png", dict(fx=5, fy=5, cx="left", cy=1)), (422, "cx")),
    "some intrinsics": ((GOOD_PNG, "image/png", dict(fx=5, fy=5)), (422, "without cx, cy")),
    "unknown field": ((GOOD_PNG, "image/png", dict(fxx=5)), (422, "'fxx'")),
    "control character name": ((GOOD_PNG, "image/png", dict(name="a\nb")), (422, "name")),
}


@pytest.mark.parametrize("request_parts, refusal", BAD_REQUESTS.values(), ids=BAD_REQUESTS)
def test_a_bad_request_is_one_4xx_line_and_the_next_good_one_is_answered(
    server, request_parts, refusal
):
    body, content_type, fields = request_parts
    status, words = refusal
    with server.client() as client:
        response = post(client, body, content_type, **fields)
        assert response.status_code == status, response.text
        message = response.json()["error"]
        assert words in message and "\n" not in message
        assert client.get("/v1/health").json()["pending"] == 0  # its place is free again
        assert post(client, GOOD_PNG).status_code == 200


def test_health_counts_every_refusal_the_service_answers(server):
    with server.client() as client:
        before = client.get("/v1/health").json()
        statuses = [post(client, b"hello, I am text").status_code for _ in range(3)]
        statuses += [post(client, GOOD_PNG, "text/plain").status_code for _ in range(3)]
        statuses.append(post(client, GOOD_PNG, fxx=5).status_code)
        statuses.append(client.get("/v1/nowhere").status_code)
        assert post(client, GOOD_PNG).status_code == 200
        after = client.get("/v1/health").json()
    assert statuses == [400] * 3 + [415] * 3 + [422, 404]
    assert after["refused"] == before["refused"] + len(statuses)
    assert after["answered"] == before["answered"] + 1


def test_a_path_named_by_the_caller_is_never_read(server, model):
    # The model file's own path as the body, as a field, as a URL: none is read.
    with server.client() as client:
        assert post(client, str(model).encode()).status_code == 400
        assert post(client, GOOD_PNG, name=str(model)).json()["name"] == str(model)
        assert client.get(f"/v1/model/{model}").status_code == 404


def test_unknown_paths_and_methods_are_one_line_too(server):
    with server.client() as client:
        missing = client.get("/v1/nowhere")
        wrong = client.get("/v1/localize")
    assert missing.status_code == 404 and missing.json() == {"error": "Not Found"}
    assert wrong.status_code == 405 and "error" in wrong.json()


def test_the_client_raises_the_services_message(server):
    with (
        Client(server.url) as client,
        pytest.raises(ServiceError, match="^400: the request body is empty"),
    ):
        client.localize(b"")
    with Client(server.url) as client, pytest.raises(ServiceError) as refused:
        client.localize(b"\x89PNG\r\n\x1a\n")
    assert refused.value.status == 400 and "header" in refused.value.message


def test_the_openapi_schema_documents_the_endpoints(server):
    with server.client() as client:
        schema = client.get("/openapi.json").json()
    localize = schema["paths"]["/v1/localize"]["post"]
    assert set(localize["requestBody"]["content"]) == {"image/png", "image/jpeg"}
    assert {p["name"] for p in localize["parameters"]} == {"fx", "fy", "cx", "cy", "name"}
    assert {"/v1/health", "/v1/model"} <= set(schema["paths"])


def test_concurrent_clients_each_get_their_own_answer(server, reference):
    images = [pixels(seed) for seed in range(10, 16)]

    def ask(image):
        with Client(server.url) as client:
            return client.localize(image)

    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(ask, images))
    for image, answer in zip(images, answers, strict=True):
        assert_same_answer(dict(answer.raw), reference.localize(image))
