"""The progress of a structure build counts the map's images: the last line of each
phase reads M/M for a map of M images, never M + 1."""

from __future__ import annotations

import re

from relocfw.structure import tracks
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.features import extract_rootsift
from relocfw.structure.track_structure import build_by_track_triangulation
from relocfw.structure.tracks import TrackSettings


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


class CountingProgress:
    """Records, at each step, how many images had been matched by then."""

    def __init__(self, matched: list[int]) -> None:
        self.matched = matched
        self.at_steps: list[int] = []

    def advance(self) -> None:
        self.at_steps.append(len(self.matched))


def test_a_matching_step_is_shown_once_its_image_is_matched(synthetic_scene, monkeypatch):
    views = synthetic_scene.views[:3]
    features = [extract_rootsift(view.image, 128) for view in views]
    matched: list[int] = []
    original = tracks.match_against_views

    def counted(query, others, ratio):
        matched.append(len(others))
        return original(query, others, ratio)

    monkeypatch.setattr(tracks, "match_against_views", counted)
    progress = CountingProgress(matched)
    # Image 0 is matched with both others; images 1 and 2 have no higher partner.
    partners = [[1, 2], [0], [0]]
    poses, cameras = [v.pose for v in views], [v.camera for v in views]
    tracks.pair_matches(features, poses, cameras, partners, TrackSettings(), progress)
    assert progress.at_steps == [1, 1, 1]  # step 1 after image 0's matching, not before
