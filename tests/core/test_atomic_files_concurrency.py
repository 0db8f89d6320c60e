"""Two runs over one cache (relocfw.core.atomic_files): one run's clean-up never
removes another run's temporary while it is written, and written files get the
user's usual mode, not mkstemp's owner-only 0o600."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from relocfw.core import atomic_files
from relocfw.core.atomic_files import (
    atomic_write,
    remove_stale_temporaries,
    temporary_prefix,
    write_text_atomic,
)

pytestmark = pytest.mark.skipif(os.name != "posix", reason="flock and file modes are POSIX")

FIRST_PART = b"first half of a long build;"
SECOND_PART = b"second half"
# A writer in its own process: writes part, says so, waits to be told to finish.
# It loads the module from its file (standard library only), not through relocfw's
# package, whose imports (torch) would take seconds.
WRITER = f"""
import importlib.util, sys, time
from pathlib import Path
spec = importlib.util.spec_from_file_location("atomic_files", sys.argv[4])
atomic_files = importlib.util.module_from_spec(spec)
spec.loader.exec_module(atomic_files)
target, ready, go = (Path(a) for a in sys.argv[1:4])
with atomic_files.atomic_write(target) as stream:
    stream.write({FIRST_PART!r})
    stream.flush()
    ready.write_text("writing")
    while not go.exists():
        time.sleep(0.01)
    stream.write({SECOND_PART!r})
"""


def start_writer(folder: Path) -> tuple[subprocess.Popen, Path, Path]:
    """A writer process of folder/map.npz, once its temporary holds the first part."""
    target, ready, go = folder / "map.npz", folder / "ready", folder / "go"
    module = Path(atomic_files.__file__)
    writer = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(target), str(ready), str(go), str(module)],
        stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 60
    while not ready.exists():
        assert writer.poll() is None, writer.stderr.read().decode()
        assert time.monotonic() < deadline, "the writer did not start"
        time.sleep(0.01)
    return writer, target, go


def temporaries_of(target: Path) -> list[Path]:
    return sorted(target.parent.glob(f"{temporary_prefix(target)}*"))


def make_old(path: Path, seconds: float = 3 * 86400) -> None:
    """Set the file's times `seconds` into the past (beyond every grace age)."""
    past = time.time() - seconds
    os.utime(path, (past, past))


@pytest.mark.parametrize("aged", [False, True], ids=["fresh", "older_than_grace"])
def test_a_second_runs_clean_up_leaves_a_live_writers_temporary(tmp_path, aged):
    writer, target, go = start_writer(tmp_path)
    try:
        (temporary,) = temporaries_of(target)
        if aged:
            # A long build: only the writer's lock can tell it is still alive.
            make_old(temporary)
        remove_stale_temporaries(target)
        assert temporary.exists(), "the live writer's temporary was removed"
    finally:
        go.write_text("finish")
        _, errors = writer.communicate(timeout=60)
    assert writer.returncode == 0, errors.decode()
    assert target.read_bytes() == FIRST_PART + SECOND_PART
    assert temporaries_of(target) == []


def test_a_killed_writers_temporary_is_removed_once_past_the_grace_age(tmp_path):
    writer, target, go = start_writer(tmp_path)
    writer.send_signal(signal.SIGKILL)
    writer.communicate(timeout=60)
    (temporary,) = temporaries_of(target)
    remove_stale_temporaries(target)
    # Just killed: it could be a writer between mkstemp and its lock, so it stays.
    assert temporary.exists()
    make_old(temporary)
    remove_stale_temporaries(target)
    assert not temporary.exists()
    assert not target.exists()


@pytest.mark.parametrize(
    ("umask", "expected"),
    [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)],
    ids=["umask022", "umask077", "umask002"],
)
def test_written_files_get_the_usual_mode_of_a_new_file(tmp_path, umask, expected):
    target = tmp_path / "results.json"
    old = os.umask(umask)
    try:
        write_text_atomic("{}", target)
        first = target.stat().st_mode & 0o777
        target.chmod(0o600)  # as an older relocfw wrote it
        with atomic_write(target, "w") as stream:
            stream.write("{}")
        replaced = target.stat().st_mode & 0o777
    finally:
        os.umask(old)
    assert (first, replaced) == (expected, expected)
