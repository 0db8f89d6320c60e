"""Structure from the synthetic room's rendered depth recovers a query's known pose."""

from __future__ import annotations

import numpy as np
import pytest

from relocfw.core.geometry import orientation_error_deg, pose_from_matrix
from relocfw.data.depth import write_depth
from relocfw.data.room import Room, RoomRenderer
from relocfw.data.synthetic import SyntheticSceneSpec, lap_poses, scene_laps
from relocfw.structure import MapView, build_from_depth, localize_against

WIDTH, HEIGHT = 640, 480  # at 320 x 240 SIFT's keypoints alone cost about a centimetre


@pytest.fixture(scope="module")
def room_views(tmp_path_factory):
    """Two queries from the test lap, which runs between the training laps, and the
    map views of the first training lap nearest to them (with depth maps on disk);
    only those are rendered, since rendering dominates the test's time."""
    pytest.importorskip("poselib")
    folder = tmp_path_factory.mktemp("room")
    room = Room()
    renderer = RoomRenderer(room, seed=0)
    camera = renderer.camera(WIDTH, HEIGHT)
    train_laps, test_lap = scene_laps(SyntheticSceneSpec(seed=0))
    lap = [pose_from_matrix(m) for m in lap_poses(train_laps[0], 12, room)]
    query_matrices = lap_poses(test_lap, 12, room)[:2]
    views, queries = [], []
    for matrix in query_matrices:
        truth = pose_from_matrix(matrix)
        nearest = np.argsort([np.linalg.norm(p.position - truth.position) for p in lap])[:3]
        keyframes = []
        for i in nearest:
            names = [v.name for v in views]
            if f"map {i}" not in names:
                matrix_i = lap_poses(train_laps[0], 12, room)[i]
                depth_path = folder / f"map-{i}.depth.png"
                write_depth(depth_path, renderer.depth(matrix_i, WIDTH, HEIGHT))
                image = renderer.render(matrix_i, WIDTH, HEIGHT)
                views.append(MapView(image, lap[i], camera, depth_path, f"map {i}"))
            keyframes.append([v.name for v in views].index(f"map {i}"))
        queries.append((renderer.render(matrix, WIDTH, HEIGHT), truth, keyframes))
    return views, queries, camera


def test_a_query_between_the_laps_is_localized_to_a_centimetre(room_views):
    views, queries, camera = room_views
    structure = build_from_depth(views, max_features=1024, quiet=True)
    assert not structure.skipped_views
    for image, truth, keyframes in queries:
        answer = localize_against(structure, image, camera, keyframes)
        assert answer.success, answer
        # Measured: 2.4 mm / 0.04 deg and 0.7 mm / 0.01 deg.
        assert np.linalg.norm(answer.pose.position - truth.position) < 0.01
        assert orientation_error_deg(answer.pose.quaternion, truth.quaternion) < 0.5
