"""Files written all or nothing (relocfw.core.atomic_files), still importable from
their first path, relocfw.model.checkpoints."""

import os
import time

import pytest

from relocfw.core import atomic_files
from relocfw.core.atomic_files import atomic_write, remove_stale_temporaries, write_text_atomic


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "results" / "summary.csv"
    write_text_atomic("a,b\r\n1,2\n", path)  # the folder is made; newlines as given
    assert path.read_bytes() == b"a,b\r\n1,2\n"
    with pytest.raises(RuntimeError), atomic_write(path, "w") as stream:
        stream.write("half")
        raise RuntimeError("killed")
    assert path.read_bytes() == b"a,b\r\n1,2\n"
    assert [p.name for p in path.parent.iterdir()] == ["summary.csv"]


def test_a_killed_writers_temporaries_are_removed_and_nothing_else(tmp_path):
    path = tmp_path / "model.pt"
    with atomic_write(path) as stream:
        stream.write(b"whole")
    (tmp_path / ".model.pt.x1y2").write_bytes(b"half")
    (tmp_path / ".other.pt.x1y2").write_bytes(b"someone else's")
    # Older than any grace age a live writer's temporary is given; no lock on them.
    for stale in tmp_path.glob(".*"):
        os.utime(stale, (time.time() - 3 * 86400,) * 2)
    remove_stale_temporaries(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.pt.x1y2", "model.pt"]


def test_the_old_import_path_names_the_same_functions():
    from relocfw.model import checkpoints

    for name in ("atomic_write", "write_text_atomic", "remove_stale_temporaries"):
        assert getattr(checkpoints, name) is getattr(atomic_files, name)


def test_a_file_system_that_refuses_a_mode_change_still_gets_the_file(tmp_path, monkeypatch):
    # exFAT and vfat answer EPERM to a chmod that changes the r/x bits: the data must land.
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(atomic_files.os, "fchmod", refuse)
    monkeypatch.setattr(atomic_files.os, "chmod", refuse)
    write_text_atomic("kept", tmp_path / "results.txt")
    assert (tmp_path / "results.txt").read_text() == "kept"


def test_a_folder_is_published_whole_and_a_concurrent_winner_is_kept(tmp_path):
    staging, folder = tmp_path / ".staging-1", tmp_path / "scene"
    staging.mkdir()
    (staging / "done.json").write_text("first")
    atomic_files.publish_folder(staging, folder, "done.json")
    assert (folder / "done.json").read_text() == "first" and not staging.exists()
    # A second writer finishing later keeps the first one's folder.
    late = tmp_path / ".staging-2"
    late.mkdir()
    (late / "done.json").write_text("second")
    (late / "more").write_text("x")
    atomic_files.publish_folder(late, folder, "done.json")
    assert (folder / "done.json").read_text() == "first"
    # A folder in the way that is not a finished one is not silently kept.
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "stray").write_text("x")
    with pytest.raises(OSError):
        atomic_files.publish_folder(late, tmp_path / "other", "done.json")
