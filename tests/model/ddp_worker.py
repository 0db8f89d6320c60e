"""Trains tiny models; run alone or under torchrun by test_distributed.py.

    python tests/model/ddp_worker.py OUT_DIR                       # one process
    torchrun --standalone --nproc-per-node=2 tests/model/ddp_worker.py OUT_DIR

Two scenarios, each in its own folder (checkpoints are written by rank 0 only):

- OUT_DIR/plain: a network with neither batch normalisation nor dropout, so two
  processes on halves of each batch must reproduce one process on the whole batch up
  to float rounding. Writes losses-rank{R}.json and model.pt.
- OUT_DIR/dropout: the same network with dropout, trained three times: uninterrupted;
  stopped by an exception in step 5, after the checkpoint of step 4 (as a crash
  would); and resumed from that checkpoint. Records, per rank, the dropout mask and
  the images of every step. Writes dropout-rank{R}.json, and interrupted.pt (a copy
  of the incomplete checkpoint, for a resume with the wrong number of processes).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from relocfw.core.interfaces import Backbone
from relocfw.core.values import Pose
from relocfw.model.distributed import World
from relocfw.model.pose_head import PoseHead
from relocfw.model.training import TrainingImages, TrainingRun, TrainSettings, train_backbone

PLAIN = TrainSettings(iterations=6, batch_size=8, lr=0.05, checkpoint_every=2, seed=3)
DROPOUT = TrainSettings(iterations=6, batch_size=8, lr=0.05, checkpoint_every=2, seed=4)
CRASH_STEP = 5  # the checkpoint before it holds step 4


class CrashError(Exception):
    """Stands for a crash: raised by every process in the same step."""


class TinyConvPose(Backbone):
    input_size = 16
    feature_dim = 12

    def __init__(self, dropout: float = 0.0, crash_step: int | None = None) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 3, stride=2)
        self.head = PoseHead(8, self.feature_dim, dropout=0.0)
        self.dropout = dropout
        self.crash_step = crash_step
        self.batch_sizes: list[int] = []
        self.rows: list[list[float]] = []  # per step: a fingerprint of each image seen
        self.masks: list[list[list[bool]]] = []  # per step: the units kept, per image

    def forward(self, images: torch.Tensor):
        if self.crash_step is not None and len(self.batch_sizes) + 1 == self.crash_step:
            # Before any collective of this step, so no process waits for another.
            raise CrashError
        self.batch_sizes.append(len(images))
        self.rows.append(images.flatten(1).sum(1).tolist())
        pooled = torch.relu(self.conv(images)).mean(dim=(2, 3))
        if self.dropout and self.training:
            # Dropout as an explicit mask drawn from torch's stream, so it can be recorded.
            kept = torch.nn.functional.dropout(torch.ones_like(pooled), self.dropout)
            self.masks.append((kept != 0).tolist())
            pooled = pooled * kept
        return self.head(pooled, self.to_world_positions)


def training_data() -> TrainingImages:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, size=(18, 24, 3), dtype=np.uint8) for _ in range(10)]
    quaternions = rng.normal(size=(10, 4))
    poses = [Pose(rng.normal(size=3), q / np.linalg.norm(q)) for q in quaternions]
    return TrainingImages(images, poses, TinyConvPose.input_size)


def flat_weights(backbone: torch.nn.Module) -> list[float]:
    return torch.cat([p.detach().flatten() for p in backbone.parameters()]).tolist()


def train(
    backbone: TinyConvPose, settings: TrainSettings, checkpoint: Path, world: World | None
) -> TrainingRun:
    return train_backbone(
        backbone, training_data(), settings, checkpoint, "tiny", quiet=True, world=world
    )


def plain(out: Path, world: World | None, rank: int) -> None:
    torch.manual_seed(0)
    backbone = TinyConvPose()
    initial = flat_weights(backbone)
    run = train(backbone, PLAIN, out / "model.pt", world)
    record = {
        "losses": run.losses,
        "weights": flat_weights(backbone),
        "initial": initial,
        "batch_sizes": backbone.batch_sizes,
    }
    (out / f"losses-rank{rank}.json").write_text(json.dumps(record))


def dropout(out: Path, world: World | None, rank: int) -> None:
    torch.manual_seed(0)
    uninterrupted = TinyConvPose(dropout=0.5)
    full = train(uninterrupted, DROPOUT, out / "uninterrupted.pt", world)

    torch.manual_seed(0)
    try:
        train(TinyConvPose(dropout=0.5, crash_step=CRASH_STEP), DROPOUT, out / "run.pt", world)
    except CrashError:
        pass
    else:
        raise AssertionError("the run was not interrupted")
    if rank == 0:
        shutil.copy(out / "run.pt", out / "interrupted.pt")
    if world is not None:
        world.barrier()  # the copy is made before the resumed run overwrites run.pt
    resumed = TinyConvPose(dropout=0.5)  # its weights come from the checkpoint
    again = train(resumed, DROPOUT, out / "run.pt", world)

    record = {
        "losses": full.losses,
        "weights": flat_weights(uninterrupted),
        "rows": uninterrupted.rows,
        "masks": uninterrupted.masks,
        "resumed_from": again.resumed_from,
        "resumed_losses": again.losses,
        "resumed_weights": flat_weights(resumed),
        "resumed_masks": resumed.masks,
    }
    (out / f"dropout-rank{rank}.json").write_text(json.dumps(record))


def main(out: Path) -> None:
    world = None
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        dist.init_process_group("gloo")
        world = World.current()
    rank = 0 if world is None else world.rank
    for scenario in (plain, dropout):
        folder = out / scenario.__name__
        folder.mkdir(parents=True, exist_ok=True)
        scenario(folder, world, rank)
    if world is not None:
        dist.destroy_process_group()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
