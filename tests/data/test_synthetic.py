import hashlib
import json
from dataclasses import asdict

import cv2
import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.geometry import pose_to_matrix
from relocfw.core.imaging import read_rgb
from relocfw.data.depth import read_frame_depth
from relocfw.data.intrinsics import read_intrinsics_matrix
from relocfw.data.room import Room, RoomRenderer
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.data.synthetic import (
    RENDERER_VERSION,
    SyntheticScene,
    SyntheticSceneSpec,
    ensure_synthetic_scene,
    look_rotation,
)

# The conftest's tiny_scene spec.
TINY_SPEC = {
    "width": 48,
    "height": 36,
    "train_laps": 2,
    "train_frames_per_lap": 8,
    "test_frames": 4,
}


def test_scene_is_written_in_the_7scenes_layout(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    assert len(train) == 16 and len(test) == 4
    assert read_rgb(train[0].image_path).shape == (36, 48, 3)


def test_train_and_test_laps_do_not_coincide(tiny_scene):
    train = np.stack([f.pose.position for f in load_sevenscenes(tiny_scene, None, "train")])
    test = np.stack([f.pose.position for f in load_sevenscenes(tiny_scene, None, "test")])
    gaps = np.linalg.norm(test[:, None] - train[None], axis=2).min(axis=1)
    assert gaps.min() > 0.02


def test_scene_is_cached(tiny_scene):
    spec = SyntheticSceneSpec(
        width=48, height=36, train_laps=2, train_frames_per_lap=8, test_frames=4
    )
    before = (tiny_scene / "scene.json").stat().st_mtime_ns
    assert ensure_synthetic_scene(spec, tiny_scene.parents[1], quiet=True) == tiny_scene
    assert (tiny_scene / "scene.json").stat().st_mtime_ns == before


def test_rendering_is_projective():
    """A wall seen head-on: moving closer magnifies it by the ratio of distances."""
    room = Room(boxes=())
    renderer = RoomRenderer(room, seed=3)
    rotation = look_rotation(0.0, 0.0, 0.0)  # looking along +x, at the x = 8 wall
    assert np.allclose(rotation[:, 2], [1, 0, 0])

    def view(distance):
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = [room.size[0] - distance, 3.0, 1.5]
        return renderer.render(pose, 160, 120, supersample=1).astype(float)

    far, near = view(4.0), view(2.0)
    # The central 80x60 of the far view is the whole near view, shrunk by 2.
    shrunk = cv2.resize(near, (80, 60), interpolation=cv2.INTER_AREA)
    centre = far[30:90, 40:120]
    assert np.corrcoef(shrunk.ravel(), centre.ravel())[0, 1] > 0.9
    other = far[0:60, 0:80]
    assert np.corrcoef(shrunk.ravel(), other.ravel())[0, 1] < 0.5


# The colour images and poses of the tiny scene (48x36, two laps of 8, a test lap of
# 4, seed 0) as the code before depth rendering wrote them. Taken on the tree of
# commit f41c4e7 (no depth yet), numpy 2.4.6 and OpenCV 5.0.0, by rendering that spec
# with ensure_synthetic_scene and running `colour_and_pose_digest` (this file's
# function, unchanged) on the folder. Adding depth must not change a single pixel or
# pose digit. A different numpy/OpenCV build could in principle round a pixel
# differently; then re-take it with the older code, not with this one.
COLOUR_AND_POSES_BEFORE_DEPTH = "87d21179d8298eafc6d34e3a6948e86227b98809be088a8807e0805bf1eb55cb"


def colour_and_pose_digest(folder) -> str:
    """sha256 over every frame's decoded pixels and pose file bytes, train then test."""
    digest = hashlib.sha256()
    for split in ("train", "test"):
        for frame in load_sevenscenes(folder, None, split):
            digest.update(cv2.imread(str(frame.image_path), cv2.IMREAD_UNCHANGED).tobytes())
            pose_file = frame.image_path.name.replace(".color.png", ".pose.txt")
            digest.update(frame.image_path.with_name(pose_file).read_bytes())
    return digest.hexdigest()


DIGEST_TAKEN_WITH = ("2.4.6", "5.0.0")  # numpy, OpenCV


def test_colour_images_and_poses_are_those_rendered_before_depth(tiny_scene):
    versions = (np.__version__, cv2.__version__)
    if versions != DIGEST_TAKEN_WITH:
        pytest.skip(f"digest taken with numpy/OpenCV {DIGEST_TAKEN_WITH}, here {versions}")
    assert colour_and_pose_digest(tiny_scene) == COLOUR_AND_POSES_BEFORE_DEPTH


def test_frames_carry_the_renderers_camera_and_their_depth(tiny_scene):
    frames = SyntheticScene(tiny_scene.parents[1], quiet=True, **TINY_SPEC).frames("test")
    assert all(f.camera == RoomRenderer.camera(48, 36) for f in frames)
    assert frames[0].camera == PinholeCamera(43.875, 43.875, 23.5, 17.5, 48, 36)
    for frame in frames:
        assert frame.depth_path == frame.image_path.with_name(
            frame.image_path.name.replace(".color.png", ".depth.png")
        )
        depth = read_frame_depth(frame)
        assert depth.shape == (36, 48) and not np.isnan(depth).any()  # a closed room


def distance_to_surfaces(points: np.ndarray, room: Room) -> np.ndarray:
    """[N] metres from each point to the nearest wall, floor, ceiling or box face."""
    walls = np.minimum(points - 0.0, np.asarray(room.size) - points).min(axis=1)
    nearest = np.abs(walls)
    for box in room.boxes:
        low, high = np.asarray(box.low), np.asarray(box.high)
        outside = np.linalg.norm(np.maximum(0, np.maximum(low - points, points - high)), axis=1)
        inside = np.minimum(points - low, high - points).min(axis=1)  # > 0 inside only
        nearest = np.minimum(nearest, np.where(inside > 0, inside, outside))
    return nearest


def test_depth_lifts_every_pixel_onto_the_rooms_surfaces(tiny_scene):
    """z along the optical axis: through K and the pose, each pixel lands on a face.

    A depth of the ray length instead would put off-centre pixels up to 30% too far,
    and a principal point half a pixel off would slide them off box edges.
    """
    frames = load_sevenscenes(tiny_scene, None, "train")[::5]
    room = Room()
    for frame in frames:
        depth = read_frame_depth(frame).astype(np.float64)
        rows, cols = np.indices(depth.shape)
        k_inverse = np.linalg.inv(frame.camera.matrix())
        pixels = np.stack([cols.ravel(), rows.ravel(), np.ones(depth.size)])
        in_camera = (k_inverse @ pixels) * depth.ravel()  # [3, N]; z is the depth
        pose = pose_to_matrix(frame.pose)
        points = (pose[:3, :3] @ in_camera).T + pose[:3, 3]
        # 1 mm: half a millimetre of rounding, the rest float32 poses on disk.
        assert distance_to_surfaces(points, room).max() < 1e-3


def test_depth_is_the_distance_along_the_axis_not_the_ray():
    room = Room(boxes=())
    renderer = RoomRenderer(room, seed=3)
    pose = np.eye(4)
    pose[:3, :3] = look_rotation(0.0, 0.0, 0.0)  # facing the x = 8 wall head-on
    # 2 m away the whole view is that wall (at 4 m the corners would see the ceiling).
    pose[:3, 3] = [room.size[0] - 2.0, 3.0, 1.5]
    depth = renderer.depth(pose, 16, 12)
    assert depth.shape == (12, 16) and np.allclose(depth, 2.0, atol=1e-12)


def test_the_camera_does_not_depend_on_supersampling():
    # Rendering at twice the size and area-averaging down keeps pixel edges on pixel
    # edges, so the big image's camera scaled down is the small image's.
    big = RoomRenderer.camera(96, 72).scaled_to(48, 36)
    small = RoomRenderer.camera(48, 36)
    assert np.allclose(big.matrix(), small.matrix(), atol=1e-12)


def test_depth_maps_and_intrinsics_file_are_in_the_7scenes_format(tiny_scene):
    depth = cv2.imread(str(tiny_scene / "seq-01" / "frame-000003.depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (36, 48)
    assert depth.min() > 1000 and depth.max() < 11000  # millimetres inside an 8 x 6 x 3 room
    camera = read_intrinsics_matrix(tiny_scene / "camera-intrinsics.txt", 48, 36)
    assert camera == RoomRenderer.camera(48, 36)


def test_a_cache_from_before_depth_is_not_reused(tmp_path):
    spec = SyntheticSceneSpec(**TINY_SPEC)
    versions = {"renderer": RENDERER_VERSION}  # the old key: no layout version
    old_text = json.dumps({**asdict(spec), **versions}, sort_keys=True)
    old_key = hashlib.sha256(old_text.encode()).hexdigest()[:12]
    assert old_key == "9c23f19b483b"  # the folder name the code before depth used
    assert spec.key() != old_key
