"""The structure map and the query solve on real 7-Scenes frames (Red Kitchen).

Skipped where /work/shared/data/7scenes-redkitchen (../shared/data from the
repository) is absent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from relocfw.core.camera import SEVENSCENES_DEFAULT
from relocfw.core.geometry import orientation_error_deg, pose_from_matrix
from relocfw.core.imaging import read_rgb
from relocfw.data.sevenscenes import read_pose_file
from relocfw.structure.depth_structure import build_from_depth
from relocfw.structure.map_view import MapView
from relocfw.structure.query_solver import keyframes_by_pose, localize_against

SEQUENCE = (
    Path(__file__).resolve().parents[3]
    / "shared"
    / "data"
    / "7scenes-redkitchen"
    / "redkitchen"
    / "seq-01"
)

pytestmark = pytest.mark.skipif(not SEQUENCE.is_dir(), reason=f"{SEQUENCE} is absent")


def frame_view(number: int) -> MapView:
    stem = SEQUENCE / f"frame-{number:06d}"
    return MapView(
        read_rgb(Path(f"{stem}.color.jpg")),
        pose_from_matrix(read_pose_file(Path(f"{stem}.pose.txt")), f"{stem}.pose.txt"),
        SEVENSCENES_DEFAULT,
        Path(f"{stem}.depth.png"),
        f"seq-01/frame-{number:06d}",
    )


def test_a_frame_between_map_frames_is_localized_within_centimetres():
    structure = build_from_depth([frame_view(n) for n in range(0, 100, 20)], 1024, quiet=True)
    assert structure.skipped_views == ()
    assert (structure.point_counts() > 500).all()
    query = frame_view(30)
    keyframes = keyframes_by_pose(structure, query.pose, 3)
    answer = localize_against(structure, query.image, query.camera, keyframes)
    assert answer.success and answer.inliers > 100
    assert np.linalg.norm(answer.pose.position - query.pose.position) < 0.05
    assert orientation_error_deg(answer.pose.quaternion, query.pose.quaternion) < 2.0
