"""What a compact map cache entry must be to be reused or opened: the content its
map.json records (an array rewritten at the same size is noticed and the entry
rewritten), and image names that are UTF-8 (refused on opening, naming the file)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.structure.compact_cache import cached_compact_map, compact_folder
from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_writer import save_compact_map


def test_an_array_rewritten_at_the_same_size_is_not_reused(depth_structure, tmp_path, capsys):
    first = cached_compact_map(tmp_path, "key", depth_structure, quiet=True)
    expected = first.camera_points(0).copy()
    folder = compact_folder(tmp_path, "key")
    points = np.load(folder / "points.npy")
    size = (folder / "points.npy").stat().st_size
    points[:, 2] += 100  # every point 100 m farther: the same shape, dtype and bytes
    np.save(folder / "points.npy", points)
    assert (folder / "points.npy").stat().st_size == size
    capsys.readouterr()
    again = cached_compact_map(tmp_path, "key", depth_structure, quiet=True)
    note = capsys.readouterr().err
    assert "points.npy" in note and "rewriting" in note, note
    assert np.array_equal(again.camera_points(0), expected)


def test_an_untouched_entry_is_reused_without_a_note(depth_structure, tmp_path, capsys):
    cached_compact_map(tmp_path, "key", depth_structure, quiet=True)
    version = compact_folder(tmp_path, "key").resolve()
    cached_compact_map(tmp_path, "key", depth_structure, quiet=True)
    assert capsys.readouterr().err == ""
    assert compact_folder(tmp_path, "key").resolve() == version


def test_names_that_are_not_utf8_are_refused_on_opening(depth_structure, tmp_path):
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    names = np.load(folder / "names.npy")
    names[1] = b"view-\xff"  # the same itemsize: map.json's size still holds
    np.save(folder / "names.npy", names)
    meta = json.loads((folder / "map.json").read_text())
    assert meta["file_bytes"]["names.npy"] == (folder / "names.npy").stat().st_size
    with pytest.raises(DataError, match=r"names\.npy: name 1 is not UTF-8") as caught:
        CompactMap.open(folder)
    assert str(caught.value).startswith(str(folder))
