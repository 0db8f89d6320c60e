"""Trains a tiny deterministic model; run alone or under torchrun by test_distributed.py.

    python tests/ddp_worker.py OUT_DIR                       # one process
    torchrun --standalone --nproc-per-node=2 tests/ddp_worker.py OUT_DIR

Writes OUT_DIR/losses-rank{R}.json and the checkpoint OUT_DIR/model.pt (rank 0 only).
The network has neither batch normalisation nor dropout, so two processes on halves
of each batch must reproduce one process on the whole batch up to float rounding.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from relocfw.distributed import World
from relocfw.interfaces import Backbone
from relocfw.pose_head import PoseHead
from relocfw.training import TrainingImages, TrainSettings, train_backbone
from relocfw.values import Pose


class TinyConvPose(Backbone):
    input_size = 16
    feature_dim = 12

    def __init__(self) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 3, stride=2)
        self.head = PoseHead(8, self.feature_dim, dropout=0.0)
        self.batch_sizes: list[int] = []

    def forward(self, images: torch.Tensor):
        self.batch_sizes.append(len(images))
        pooled = torch.relu(self.conv(images)).mean(dim=(2, 3))
        return self.head(pooled, self.to_world_positions)


def training_data() -> TrainingImages:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, size=(18, 24, 3), dtype=np.uint8) for _ in range(10)]
    quaternions = rng.normal(size=(10, 4))
    poses = [Pose(rng.normal(size=3), q / np.linalg.norm(q)) for q in quaternions]
    return TrainingImages(images, poses, TinyConvPose.input_size)


def main(out: Path) -> None:
    world = None
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        dist.init_process_group("gloo")
        world = World.current()
    torch.manual_seed(0)
    backbone = TinyConvPose()
    initial = torch.cat([p.detach().flatten() for p in backbone.parameters()])
    settings = TrainSettings(iterations=6, batch_size=8, lr=0.05, checkpoint_every=2, seed=3)
    run = train_backbone(
        backbone, training_data(), settings, out / "model.pt", "tiny", quiet=True, world=world
    )
    rank = 0 if world is None else world.rank
    weights = torch.cat([p.detach().flatten() for p in backbone.parameters()])
    (out / f"losses-rank{rank}.json").write_text(
        json.dumps(
            {
                "losses": run.losses,
                "weights": weights.tolist(),
                "initial": initial.tolist(),
                "batch_sizes": backbone.batch_sizes,
            }
        )
    )
    if world is not None:
        dist.destroy_process_group()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
