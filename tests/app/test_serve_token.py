"""serve.token_file: without the token (or with another) every endpoint but the
health check answers 401; the token is compared in constant time."""

from __future__ import annotations

import hmac

import httpx
import pytest

from relocfw.client import Client, ServiceError
from relocfw.core.errors import ConfigError
from relocfw.serve.auth import BearerToken
from tests.app.test_serve_helpers import pixels, png_of, running, serve_command, tiny_model

TOKEN = "7f3a9c0e51b24d6a8e2f4c1b9d0a6e35"
IMAGE = png_of(pixels(1))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    folder = tmp_path_factory.mktemp("serve")
    token_file = folder / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    model = tiny_model(folder)
    with running(serve_command(model, f"serve.token_file={token_file}"), folder) as found:
        yield found


@pytest.mark.parametrize(
    "authorization",
    [None, "Bearer wrong-token-of-the-same-size-000", f"Basic {TOKEN}", f"Bearer {TOKEN}x", ""],
    ids=["none", "wrong", "other scheme", "longer", "empty"],
)
def test_without_the_token_localize_and_model_answer_401(server, authorization):
    headers = {"Content-Type": "image/png"}
    if authorization is not None:
        headers["Authorization"] = authorization
    with httpx.Client(base_url=server.url, timeout=30) as client:
        refused = client.post("/v1/localize", content=IMAGE, headers=headers)
        assert refused.status_code == 401
        assert refused.headers["www-authenticate"] == "Bearer"
        assert "serve.token_file" in refused.json()["error"]
        assert client.get("/v1/model", headers=headers).status_code == 401
        assert client.get("/v1/health").status_code == 200


def test_without_the_token_health_says_only_that_it_is_ready(server):
    with httpx.Client(base_url=server.url, timeout=30) as client:
        assert client.get("/v1/health").json() == {"status": "ready"}
        full = client.get("/v1/health", headers={"Authorization": f"Bearer {TOKEN}"}).json()
    assert full["status"] == "ready" and {"model_id", "pending", "refused"} <= set(full)


def test_with_a_token_the_schema_needs_it_and_the_docs_page_is_off(server):
    with httpx.Client(base_url=server.url, timeout=30) as client:
        refused = client.get("/openapi.json")
        assert refused.status_code == 401 and "serve.token_file" in refused.json()["error"]
        schema = client.get("/openapi.json", headers={"Authorization": f"Bearer {TOKEN}"})
        assert schema.status_code == 200 and "/v1/localize" in schema.json()["paths"]
        for page in ("/docs", "/redoc"):
            assert client.get(page).status_code == 404


def test_with_the_token_the_service_answers(server):
    with Client(server.url, token=TOKEN) as client:
        assert client.model()["backbone"] == "PoseNet"
        assert len(client.localize(IMAGE).position) == 3
    with Client(server.url) as client, pytest.raises(ServiceError) as refused:
        client.localize(IMAGE)
    assert refused.value.status == 401


def test_the_token_is_compared_in_constant_time(monkeypatch):
    compared = []

    def recorded(given, expected):
        compared.append((given, expected))
        return given == expected

    monkeypatch.setattr(hmac, "compare_digest", recorded)
    token = BearerToken(TOKEN)
    assert token.allows(f"Bearer {TOKEN}") and not token.allows("Bearer nope")
    assert compared == [(TOKEN.encode(), TOKEN.encode()), (b"nope", TOKEN.encode())]


@pytest.mark.parametrize(
    "text, words", [("short\n", "at least 16"), ("two words here, long enough", "one word")]
)
def test_a_weak_token_file_is_refused_naming_the_key(tmp_path, text, words):
    path = tmp_path / "token"
    path.write_text(text)
    path.chmod(0o600)
    with pytest.raises(ConfigError, match=rf"^serve\.token_file=.*{words}"):
        BearerToken.from_file(path)


# 0444: a Docker secret's default mode; 0644: a Kubernetes Secret volume's; 0440: one
# with the pod's fsGroup.
@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660, 0o444, 0o440])
def test_a_token_file_other_users_can_read_is_refused_saying_chmod_600(tmp_path, mode):
    path = tmp_path / "token"
    path.write_text(TOKEN)
    path.chmod(mode)
    with pytest.raises(ConfigError, match=rf"^serve\.token_file={path}: .*chmod 600 {path}") as no:
        BearerToken.from_file(path)
    # How to meet the rule where the file is a mounted secret.
    assert "defaultMode: 0400" in str(no.value) and "Docker secret" in str(no.value)
    for private in (0o600, 0o400):
        path.chmod(private)
        assert BearerToken.from_file(path).allows(f"Bearer {TOKEN}")
    path.chmod(0o600)


def test_a_missing_token_file_is_refused_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"^serve\.token_file=.*cannot read it"):
        BearerToken.from_file(tmp_path / "absent")
