"""How a compact map is published where the usual means are missing: a file system
that refuses symbolic links (vfat, exFAT, SMB, Windows) gets a plain folder; a
failed publish leaves no version behind; two writers whose lock does nothing (flock
on NFS) never leave the map's name on a deleted version; without flock (Windows) no
folder is opened for a lock."""

from __future__ import annotations

import errno
import os
import sys
import time

import numpy as np
import pytest

from relocfw.core import atomic_files
from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_writer import save_compact_map

fcntl = pytest.importorskip("fcntl")  # POSIX: flock

pytestmark = pytest.mark.skipif(os.name != "posix", reason="links and flock are POSIX here")


def names_beside(folder):
    """What is beside the map besides the map itself (its current version, its lock)."""
    return sorted(p.name for p in folder.parent.iterdir() if p != folder)


def versions_beside(folder):
    return [name for name in names_beside(folder) if name.startswith(f".{folder.name}.version-")]


def refuse_links(monkeypatch):
    def refused(*args, **kwargs):
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "symlink", refused)


def test_without_symbolic_links_the_map_is_a_plain_folder(depth_structure, tmp_path, monkeypatch):
    refuse_links(monkeypatch)
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    save_compact_map(depth_structure, folder, None, "float32")  # replaces it
    assert folder.is_dir() and not folder.is_symlink()
    assert CompactMap.open(folder).points.dtype == np.float32
    assert versions_beside(folder) == []
    assert not [n for n in names_beside(folder) if ".staging-" in n or ".link-" in n]


def test_a_linked_map_is_replaced_by_a_plain_folder_where_links_are_refused(
    depth_structure, tmp_path, monkeypatch
):
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    assert folder.is_symlink()
    refuse_links(monkeypatch)
    save_compact_map(depth_structure, folder, None, "float32")
    assert folder.is_dir() and not folder.is_symlink()
    assert CompactMap.open(folder).points.dtype == np.float32
    assert versions_beside(folder) == []


def test_a_failed_swap_leaves_the_map_and_no_version_of_its_own(
    depth_structure, tmp_path, monkeypatch
):
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    before = names_beside(folder)
    replace = os.replace

    def swap_refused(source, target):
        if os.fspath(target) == os.fspath(folder):
            raise OSError(errno.EIO, "Input/output error")
        return replace(source, target)

    monkeypatch.setattr(os, "replace", swap_refused)
    with pytest.raises(OSError, match="Input/output error"):
        save_compact_map(depth_structure, folder, None, "float32")
    assert names_beside(folder) == before
    assert CompactMap.open(folder).points.dtype == np.float16


def test_writers_without_a_working_lock_never_leave_the_map_on_a_deleted_version(
    depth_structure, tmp_path, monkeypatch
):
    # flock that does nothing (NFS, a directory opened read-only): each writer goes on.
    def no_lock(handle, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_lock)
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    replace = os.replace
    interleaved = []

    def a_publishes_whole_before_b_swaps(source, target):
        # B has renamed its staging folder to its version; A publishes now, start to end.
        if os.fspath(target) == os.fspath(folder) and not interleaved:
            interleaved.append(source)
            save_compact_map(depth_structure, folder, None, "float32")
        return replace(source, target)

    monkeypatch.setattr(os, "replace", a_publishes_whole_before_b_swaps)
    save_compact_map(depth_structure, folder, None, "float16")  # writer B
    assert interleaved
    compact = CompactMap.open(folder)  # B swapped last: its map
    assert compact.points.dtype == np.float16 and len(compact) == len(depth_structure)
    # A's version, no longer named, stays until it is past the grace age; the next
    # writer then removes it (and never the current one).
    monkeypatch.setattr(os, "replace", replace)
    past = time.time() - 2 * 86400
    for name in versions_beside(folder):
        os.utime(tmp_path / name, (past, past))
    save_compact_map(depth_structure, folder, None, "float32")
    assert versions_beside(folder) == [folder.resolve().name]
    assert CompactMap.open(folder).points.dtype == np.float32


def test_without_flock_no_folder_is_opened_for_a_lock(depth_structure, tmp_path, monkeypatch):
    # Windows has no fcntl, and opening a folder there raises PermissionError.
    monkeypatch.setattr(atomic_files, "fcntl", None)
    opened = os.open

    def files_only(path, flags, *args, **kwargs):
        # Only the lock code's opens (shutil.rmtree opens folders on POSIX too).
        caller = sys._getframe(1).f_globals["__name__"]
        if os.path.isdir(path) and caller == atomic_files.__name__:
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return opened(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", files_only)
    folder = tmp_path / "map"
    killed = tmp_path / ".map.staging-killed"
    killed.mkdir()
    past = time.time() - 2 * 86400
    os.utime(killed, (past, past))
    save_compact_map(depth_structure, folder)
    save_compact_map(depth_structure, folder, None, "float32")
    assert CompactMap.open(folder).points.dtype == np.float32
    assert not killed.exists()
    assert names_beside(folder) == [folder.resolve().name]
