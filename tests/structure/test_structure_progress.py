"""The progress of a structure build counts the map's images: the last line of each
phase reads M/M for a map of M images, never M + 1."""

from __future__ import annotations

import re

from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.track_structure import build_by_track_triangulation


def totals(text: str, label: str) -> set[str]:
    """The totals the plain progress lines of `label` show ("label: 2/3 (...)")."""
    return set(re.findall(rf"^{re.escape(label)}[^:]*: \d+/(\d+) ", text, flags=re.MULTILINE))


def test_track_building_counts_the_maps_images(synthetic_scene, capsys):
    views = synthetic_scene.views
    build_by_track_triangulation(views, max_features=256, quiet=False)
    shown = capsys.readouterr().err
    assert totals(shown, "map structure by tracks") == {str(len(views))}, shown


def test_depth_building_counts_the_maps_images(synthetic_scene, capsys):
    views = synthetic_scene.views
    build_from_depth(views, max_features=256, quiet=False)
    shown = capsys.readouterr().err
    assert totals(shown, "map structure from depth") == {str(len(views))}, shown
