"""The serve.* options and the command's refusals: each one line naming the key."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from relocfw.core.errors import ConfigError
from relocfw.serve.service import exposure_warning, listening_socket
from relocfw.serve.settings import ServeSettings


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"port": 70000}, r"serve\.port must be in \[0, 65535\]"),
        ({"workers": 0}, r"serve\.workers must be >= 1"),
        ({"max_pending": 0}, r"serve\.max_pending must be >= 1"),
        ({"workers": 4, "max_pending": 2}, r"serve\.max_pending=2 is below serve\.workers=4"),
        ({"max_bytes": True}, r"serve\.max_bytes must be a whole number"),
        ({"host": " "}, r"serve\.host is empty"),
        ({"body_timeout_s": 0}, r"serve\.body_timeout_s must be a number > 0"),
        ({"header_timeout_s": float("nan")}, r"serve\.header_timeout_s must be a number > 0"),
        ({"shutdown_timeout_s": -1.0}, r"serve\.shutdown_timeout_s must be a number > 0"),
        ({"max_connections": 0}, r"serve\.max_connections must be >= 1"),
        ({"max_connections_per_client": 0}, r"serve\.max_connections_per_client must be >= 1"),
        ({"max_connections_per_client": 2.5}, r"serve\.max_connections_per_client must be a whole"),
        (
            {"max_connections": 4, "max_pending": 8},
            r"serve\.max_connections=4 is below serve\.max_pending=8",
        ),
    ],
)
def test_a_bad_serve_value_names_its_key(changes, words):
    with pytest.raises(ConfigError, match=words):
        ServeSettings(model=Path("m.relocfw"), **changes)


def test_the_per_client_cap_is_off_with_null():
    settings = ServeSettings(model=Path("m.relocfw"), max_connections_per_client=None)
    assert settings.max_connections_per_client is None


def test_a_port_in_use_names_host_and_port():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(
            ConfigError, match=rf"^cannot listen on serve\.host=127\.0\.0\.1 serve\.port={port}"
        ):
            listening_socket("127.0.0.1", port)


def serve_process(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "relocfw.app.tasks.serve", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_missing_model_file_ends_the_command_in_one_line(tmp_path):
    done = serve_process(str(tmp_path / "absent.relocfw"), "serve.port=0", cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "absent.relocfw" in lines[0]


def test_without_a_model_the_command_says_how_to_call_it(tmp_path):
    assert serve_process("--help", cwd=tmp_path).stdout.startswith("usage: relocfw-serve MODEL")
    done = serve_process("serve.port=1", cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.startswith("usage: relocfw-serve MODEL")


@pytest.mark.parametrize(
    "host, exposed",
    [
        ("0.0.0.0", True),
        ("::", True),
        ("192.168.1.20", True),
        ("127.0.0.1", False),
        ("127.0.0.2", False),
        ("::1", False),
    ],
)
def test_a_public_address_without_a_token_is_warned_in_one_line(host, exposed):
    warning = exposure_warning(host, token=False)
    assert (warning is not None) == exposed
    if exposed:
        assert warning.startswith(f"warning: serve.host={host} ") and "\n" not in warning
        assert "serve.token_file" in warning
    assert exposure_warning(host, token=True) is None


def test_max_connections_above_the_open_file_limit_ends_in_one_line(tmp_path):
    import resource

    def few_open_files() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))

    done = subprocess.run(
        [sys.executable, "-m", "relocfw.app.tasks.serve", str(tmp_path / "absent.relocfw")]
        + ["serve.port=0", "serve.max_connections=1000"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=few_open_files,
    )
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr[-3000:]
    assert lines[0].startswith("error: serve.max_connections=1000 ") and "ulimit -n" in lines[0]


def test_an_open_file_limit_below_the_service_itself_says_raise_it(monkeypatch):
    """A hard limit below what the service needs besides its connections: lowering
    serve.max_connections cannot help, and the message does not suggest it."""
    from relocfw.serve import connections

    monkeypatch.setattr(connections.resource, "getrlimit", lambda _: (100, 200))
    with pytest.raises(ConfigError) as refused:
        connections.reserve_open_files(256)
    message = str(refused.value)
    assert message.startswith("serve.max_connections=256 ") and "lower" not in message
    assert f"ulimit -n {connections.open_files_needed(256)}" in message


def test_an_open_file_limit_that_cannot_be_raised_is_one_config_error(monkeypatch):
    """setrlimit can refuse even below the hard limit (a container's seccomp, macOS's
    OPEN_MAX): the service stops in one line naming the key, not a traceback."""
    from relocfw.serve import connections

    def refuse(*_: object) -> None:
        raise ValueError("not allowed to raise maximum limit")

    monkeypatch.setattr(connections.resource, "getrlimit", lambda _: (100, 100_000))
    monkeypatch.setattr(connections.resource, "setrlimit", refuse)
    with pytest.raises(ConfigError, match=r"^serve\.max_connections=256 .*ulimit -n"):
        connections.reserve_open_files(256)
