"""What the benchmarks share: views of the synthetic room, map views of dataset frames
read on demand, writing their JSON."""

from __future__ import annotations

import importlib
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from relocfw import CropSearch, Relocalizer
from relocfw.core.geometry import pose_from_matrix
from relocfw.core.imaging import read_rgb
from relocfw.core.values import Pose
from relocfw.data.frames import Frame
from relocfw.data.room import Room, RoomRenderer
from relocfw.data.synthetic import (
    SyntheticSceneSpec,
    ensure_synthetic_scene,
    lap_poses,
    scene_laps,
)
from relocfw.model.checkpoints import write_text_atomic
from relocfw.structure.map_view import MapView

# Where relocfw caches scenes and checkpoints, as the CLI's cache_dir default reads it.
DEFAULT_CACHE = Path(os.environ.get("RELOCFW_CACHE", "~/.cache/relocfw"))


class LazyViews(Sequence):
    """Map views of dataset frames that read their image when asked (the structure
    builders read each once, in order), so the map's images are never all in memory."""

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> MapView:  # type: ignore[override]
        frame = self.frames[index]
        return MapView(
            read_rgb(frame.image_path),
            frame.pose,
            frame.camera,
            frame.depth_path,
            frame.name,
            frame.depth_units_per_metre,
            depth_camera=frame.depth_camera,
            depth_to_colour=frame.depth_to_colour,
        )


def render_views(
    count: int, lap_index: int, width: int = 640, height: int = 480, seed: int = 0
) -> tuple[list[np.ndarray], list[Pose]]:
    """`count` images and poses along training lap `lap_index` (-1: the test lap)."""
    room = Room()
    renderer = RoomRenderer(room, seed=seed)
    train_laps, test_lap = scene_laps(SyntheticSceneSpec(seed=seed))
    lap = test_lap if lap_index < 0 else train_laps[lap_index]
    matrices = lap_poses(lap, count, room)
    images = [renderer.render(matrix, width, height) for matrix in matrices]
    return images, [pose_from_matrix(matrix) for matrix in matrices]


def write_json(report: dict, out: Path) -> None:
    """Write a benchmark's report atomically (an earlier result is never half-replaced)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(json.dumps(report, indent=2) + "\n", out)
    print(f"written: {out}")


def model_frames(relocalizer, cache_dir: Path, split: str = "test") -> list[Frame]:
    """A split of the dataset named in a model file's metadata (relocfw.load_model)."""
    settings = dict(relocalizer.metadata["dataset_settings"])
    module, _, name = settings.pop("_target_").rpartition(".")
    dataset = getattr(importlib.import_module(module), name)(cache_dir=cache_dir, **settings)
    return dataset.frames(split)


def with_search(relocalizer: Relocalizer, search: CropSearch) -> Relocalizer:
    """A loaded pipeline with another crop search: the same network, fitted map,
    options, map poses and metadata."""
    return relocalizer.replace(search=search)


def device_name(device: str) -> str:
    """What the numbers were measured on: the GPU's name, or the CPU and its threads."""
    if torch.device(device).type == "cuda":
        return torch.cuda.get_device_name(torch.device(device))
    return f"cpu ({torch.get_num_threads()} torch threads)"


def synthetic_validation(cache_dir: Path) -> list[str]:
    """Overrides that train on the synthetic scene's laps 1-2 and validate on lap 3
    (rendered into the cache if need be): the carve every validation study uses."""
    folder = ensure_synthetic_scene(SyntheticSceneSpec(), cache_dir, quiet=True)
    return [
        "dataset=sevenscenes",
        f"dataset.root={folder}",
        "dataset.scene=null",
        "dataset.train_sequences=[1,2]",
        "dataset.test_sequences=[3]",
    ]
