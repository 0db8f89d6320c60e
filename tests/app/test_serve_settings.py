"""The serve.* options and the command's refusals: each one line naming the key."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from relocfw.core.errors import ConfigError
from relocfw.serve.service import listening_socket
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
    ],
)
def test_a_bad_serve_value_names_its_key(changes, words):
    with pytest.raises(ConfigError, match=words):
        ServeSettings(model=Path("m.relocfw"), **changes)


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
