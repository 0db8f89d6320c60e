"""The embedded scene: a robot's laps around a rendered room, in the 7-Scenes layout.

Training laps and the test lap follow the same loop but never coincide (different
radius, height, phase and head wobble), like the paper's robot experiments: two or
more laps to map, another lap to relocalize.

Like a 7-Scenes scene, the folder holds beside each `frame-NNNNNN.color.png` its
`.pose.txt` and `.depth.png` (uint16 millimetres of z along the optical axis, exact at
each pixel's centre), and `camera-intrinsics.txt` (the renderer's K for the rendered
size), so the frames come with their camera and depth (relocfw.data.sevenscenes).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from relocfw.core.atomic_files import publish_folder
from relocfw.core.errors import ConfigError
from relocfw.core.progress import Progress
from relocfw.data.depth import write_depth
from relocfw.data.frames import Frame
from relocfw.data.intrinsics import INTRINSICS_FILE, write_intrinsics_matrix
from relocfw.data.room import Room, RoomRenderer
from relocfw.data.sevenscenes import REGISTERED_MARKER, load_sevenscenes

RENDERER_VERSION = 1  # bump when rendering changes, so cached scenes are not reused
# Bump when a scene folder gains or changes files, so a cache without them is not
# reused. 2: depth maps and camera-intrinsics.txt (layout 1, no version in the key,
# had colour and poses only; its colour images and poses are the same as layout 2's).
# 3: depth-registered.txt, without which the 7-Scenes loader would take the depth
# maps for raw Kinect depth and register them (relocfw.data.sevenscenes).
LAYOUT_VERSION = 3


@dataclass(frozen=True)
class Lap:
    """One loop of the robot: path scale, camera height, phase and wobble."""

    radius_scale: float
    height: float
    phase: float
    wobble_phase: float


@dataclass(frozen=True)
class SyntheticSceneSpec:
    """What defines a rendered scene; its hash names the cache folder."""

    width: int = 160
    height: int = 120
    train_laps: int = 3
    train_frames_per_lap: int = 100
    test_frames: int = 60
    seed: int = 0

    def validate(self) -> None:
        for key in ("width", "height", "train_laps", "train_frames_per_lap", "test_frames"):
            if getattr(self, key) < 1:
                raise ConfigError(f"dataset.{key} must be >= 1, got {getattr(self, key)}")
        if min(self.width, self.height) < 16:
            raise ConfigError("dataset.width and dataset.height must be at least 16 pixels")

    def key(self) -> str:
        """12 hex digits naming the cache folder: the spec, renderer and folder layout."""
        versions = {"renderer": RENDERER_VERSION, "layout": LAYOUT_VERSION}
        text = json.dumps({**asdict(self), **versions}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


def look_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (camera x right, y down, z forward; world z up)."""
    forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, forward], axis=1)


def lap_poses(lap: Lap, frames: int, room: Room) -> list[np.ndarray]:
    """Camera-to-world matrices along one lap of an ellipse around the room's centre."""
    centre = np.array(room.size[:2]) / 2
    radii = np.array([0.325 * room.size[0], 0.283 * room.size[1]]) * lap.radius_scale
    poses = []
    for i in range(frames):
        angle = 2 * np.pi * (i + lap.phase) / frames
        position = np.array(
            [*(centre + radii * [np.cos(angle), np.sin(angle)]), lap.height], dtype=np.float64
        )
        tangent = np.arctan2(radii[1] * np.cos(angle), -radii[0] * np.sin(angle))
        wobble = angle * 3 + lap.wobble_phase
        pose = np.eye(4)
        pose[:3, :3] = look_rotation(
            tangent + 0.2 * np.sin(wobble), 0.06 * np.sin(wobble * 0.7), 0.03 * np.cos(wobble)
        )
        pose[:3, 3] = position
        poses.append(pose)
    return poses


def scene_laps(spec: SyntheticSceneSpec) -> tuple[list[Lap], Lap]:
    """Training laps spread around the loop, and a test lap that falls between them."""
    rng = np.random.default_rng(spec.seed)
    train = []
    for i in range(spec.train_laps):
        spread = (i / max(1, spec.train_laps - 1)) - 0.5 if spec.train_laps > 1 else 0.0
        train.append(
            Lap(1.0 + 0.14 * spread, 1.2 + 0.2 * spread, rng.uniform(0, 1), rng.uniform(0, 6.3))
        )
    test = Lap(1.035, 1.23, 0.5, rng.uniform(0, 6.3))
    return train, test


def write_pose(path: Path, matrix: np.ndarray) -> None:
    """A 4x4 pose file in 7-Scenes' own text format."""
    lines = ["\t".join(f"{value: .7e}" for value in row) for row in matrix]
    path.write_text("\n".join(lines) + "\n")


def ensure_synthetic_scene(spec: SyntheticSceneSpec, cache_dir: Path, quiet: bool = False) -> Path:
    """Render the scene into the cache if it is not there yet; return its folder.

    Renders into a temporary folder and renames it into place, so an interrupted
    render never leaves a half-written scene that a later run would trust. The depth
    maps are cast after each colour image with rays of their own and no random
    numbers, so the colour images and poses are those of a scene without depth.
    """
    spec.validate()
    folder = Path(cache_dir) / "scenes" / f"synthetic-{spec.key()}"
    if (folder / "scene.json").is_file():
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    room = Room()
    renderer = RoomRenderer(room, seed=spec.seed)
    train_laps, test_lap = scene_laps(spec)
    laps = [(lap, spec.train_frames_per_lap) for lap in train_laps] + [(test_lap, spec.test_frames)]
    staging = Path(tempfile.mkdtemp(prefix=".rendering-", dir=folder.parent))
    try:
        progress = Progress(sum(n for _, n in laps), "rendering synthetic scene", quiet=quiet)
        for number, (lap, frames) in enumerate(laps, start=1):
            sequence = staging / f"seq-{number:02d}"
            sequence.mkdir()
            for i, pose in enumerate(lap_poses(lap, frames, room)):
                rgb = renderer.render(pose, spec.width, spec.height)
                cv2.imwrite(str(sequence / f"frame-{i:06d}.color.png"), rgb[:, :, ::-1])
                write_pose(sequence / f"frame-{i:06d}.pose.txt", pose)
                depth = renderer.depth(pose, spec.width, spec.height)
                write_depth(sequence / f"frame-{i:06d}.depth.png", depth)
                progress.advance()
        progress.close()
        train_names = [f"sequence{i}" for i in range(1, len(train_laps) + 1)]
        (staging / "TrainSplit.txt").write_text("\n".join(train_names) + "\n")
        (staging / "TestSplit.txt").write_text(f"sequence{len(laps)}\n")
        write_intrinsics_matrix(staging / INTRINSICS_FILE, renderer.camera(spec.width, spec.height))
        # Depth and colour are cast from the same rays: the loader reads the depth maps
        # pixel for pixel and the intrinsics as the colour camera's.
        (staging / REGISTERED_MARKER).write_text(
            "The depth maps of this scene are registered to its colour images.\n"
        )
        # scene.json last: its presence marks a complete scene.
        versions = {"renderer": RENDERER_VERSION, "layout": LAYOUT_VERSION}
        (staging / "scene.json").write_text(
            json.dumps({**asdict(spec), **versions, "room": asdict(room)}, indent=2)
        )
        publish_folder(staging, folder, "scene.json")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


class SyntheticScene:
    """The embedded dataset: rendered on first use, then read from the cache.

    Its frames carry the renderer's camera (from the scene's camera-intrinsics.txt)
    and their depth maps (millimetres), as a 7-Scenes scene with depth does.

    Args:
        cache_dir: where rendered scenes are kept.
        Other arguments: see `SyntheticSceneSpec`.
    """

    def __init__(self, cache_dir: str | Path, quiet: bool = False, **spec: int) -> None:
        self.spec = SyntheticSceneSpec(**spec)
        self.spec.validate()
        self.cache_dir = Path(cache_dir).expanduser()
        self.quiet = quiet

    def frames(self, split: str) -> list[Frame]:
        folder = ensure_synthetic_scene(self.spec, self.cache_dir, quiet=self.quiet)
        return load_sevenscenes(folder, None, split)
