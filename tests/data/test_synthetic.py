import cv2
import numpy as np

from relocfw.core.imaging import read_rgb
from relocfw.data.room import Room, RoomRenderer
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.data.synthetic import SyntheticSceneSpec, ensure_synthetic_scene, look_rotation


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
