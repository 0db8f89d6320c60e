"""Two processes writing the same compact map, and a third reading it meanwhile: every
write succeeds (the last one wins), no staging folder is left, and the reader only
ever opens a whole map, one of the two written; with the writers' lock and where
flock does nothing (NFS)."""

from __future__ import annotations

import errno
import multiprocessing
import os
import time
import traceback

import numpy as np
import pytest

from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_writer import save_compact_map

fcntl = pytest.importorskip("fcntl")  # POSIX: flock

pytestmark = pytest.mark.skipif(os.name != "posix", reason="fork and symlinks are POSIX")

WRITES = 30  # per writer: a race shows within a few dozen (3 of 120 failed before)


def write_often(structure, folder, point_dtype, errors) -> None:
    for _ in range(WRITES):
        try:
            save_compact_map(structure, folder, None, point_dtype)
        except Exception:  # noqa: BLE001 (reported to the test)
            errors.put(traceback.format_exc(limit=2))


def read_often(folder, stop, errors, reads) -> None:
    count = 0
    while not stop.is_set():
        try:
            compact = CompactMap.open(folder)
            compact.keyframe_map([0, 1])
            assert compact.points.dtype in (np.float16, np.float32)
            count += 1
        except Exception:  # noqa: BLE001 (reported to the test)
            errors.put(traceback.format_exc(limit=2))
    reads.put(count)


@pytest.mark.parametrize("lock_works", [True, False])
def test_two_writers_and_a_reader_race_without_a_fault(
    depth_structure, tmp_path, monkeypatch, lock_works
):
    if not lock_works:
        # flock that does nothing (NFS): the writers race through their publishes.
        def no_lock(handle, operation):
            raise OSError(errno.ENOLCK, "No locks available")

        monkeypatch.setattr(fcntl, "flock", no_lock)
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    context = multiprocessing.get_context("fork")  # the map and imports are inherited
    errors, reads, stop = context.Queue(), context.Queue(), context.Event()
    writers = [
        context.Process(
            target=write_often, args=(depth_structure, folder, dtype, errors), daemon=True
        )
        for dtype in ("float16", "float32")
    ]
    reader = context.Process(target=read_often, args=(folder, stop, errors, reads), daemon=True)
    try:
        reader.start()
        for writer in writers:
            writer.start()
        for writer in writers:
            writer.join(timeout=120)
        stop.set()
        reader.join(timeout=60)
    finally:
        # A stuck child must not hang pytest: stopped here (its exit code then fails).
        for child in (*writers, reader):
            if child.is_alive():
                child.terminate()
                child.join(timeout=10)
    faults = []
    while not errors.empty():
        faults.append(errors.get())
    assert faults == [], faults[0]
    assert all(p.exitcode == 0 for p in (*writers, reader))
    assert reads.get(timeout=10) > 0
    # Nothing but the map is left beside it: its current version and the writers' lock.
    # Unlocked, a version two writers both replaced stays until it is an hour old.
    compact = CompactMap.open(folder)
    assert len(compact) == len(depth_structure)
    beside = sorted(p.name for p in tmp_path.iterdir())
    if lock_works:
        assert beside == beside_the_map(folder)
    else:
        others = [n for n in beside if n not in beside_the_map(folder)]
        assert set(beside_the_map(folder)) <= set(beside)
        assert all(n.startswith(".map.version-") for n in others), others


def beside_the_map(folder) -> list[str]:
    """What a map's folder holds once written: the map's name, the version it names
    and the lock file its writers take turns by."""
    return sorted([folder.name, folder.resolve().name, f".{folder.name}.lock"])


def test_a_killed_writers_staging_folder_is_cleared_by_the_next_writer(depth_structure, tmp_path):
    killed = tmp_path / ".map.staging-killed"
    killed.mkdir()
    (killed / "codes.npy").write_bytes(b"\0" * 1000)
    past = time.time() - 2 * 86400
    os.utime(killed, (past, past))
    save_compact_map(depth_structure, tmp_path / "map")
    assert not killed.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == beside_the_map(tmp_path / "map")


def test_a_map_an_older_relocfw_wrote_as_a_folder_is_replaced(depth_structure, tmp_path):
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    version = folder.resolve()
    folder.unlink()
    version.rename(folder)  # the plain folder an older relocfw published
    assert len(CompactMap.open(folder)) == len(depth_structure)
    save_compact_map(depth_structure, folder, None, "float32")
    assert folder.is_symlink() and CompactMap.open(folder).points.dtype == np.float32
    assert sorted(p.name for p in tmp_path.iterdir()) == beside_the_map(folder)
