"""Training the scene-coordinate head on its buffer (Adam, seeded, no global state).

Each step draws a random batch of buffer cells, predicts their world points and takes
the depth loss (targets measured) or the reprojection loss with its curriculum
(RGB only; relocfw.structure.scene_coordinate_losses). The learning rate warms up
linearly over the first WARMUP_SHARE of the steps, then decays on a half cosine to
zero: a high rate early moves the freshly initialised head off the scene's centre
quickly, and the decay settles the last centimetres (ACE trains with a one-cycle
schedule for the same reasons).

Randomness comes only from a torch.Generator seeded with the refiner's seed (initial
weights and batches): the same seed and buffer give the same head, and torch's own
stream is never touched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from relocfw.core.errors import ConfigError
from relocfw.core.progress import Progress
from relocfw.structure.scene_coordinate_buffer import TrainingBuffer
from relocfw.structure.scene_coordinate_head import SceneCoordinateHead, built_head
from relocfw.structure.scene_coordinate_losses import (
    curriculum_threshold,
    depth_loss,
    reprojection_loss,
)

WARMUP_SHARE = 0.05


@dataclass(frozen=True)
class TrainingSettings:
    """How the head trains.

    Attributes:
        steps: Adam steps.
        batch_size: buffer cells per step.
        lr: the peak learning rate.
        seed: initial weights and batches.
        tau_start: RGB only: the reprojection clamp at the first step, pixels.
        tau_end: ... and at the last.
        prior_depth: RGB only: where an invalid point is pulled along its ray.
    """

    steps: int
    batch_size: int
    lr: float
    seed: int
    tau_start: float = 50.0
    tau_end: float = 2.0
    prior_depth: float = 10.0


def learning_rate_factor(step: int, steps: int) -> float:
    """The share of the peak learning rate at `step`: linear warm-up, half-cosine decay."""
    warmup = max(1, int(WARMUP_SHARE * steps))
    if step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(steps - warmup, 1)
    return 0.5 * (1.0 + math.cos(math.pi * progress))


def scene_mean(buffer: TrainingBuffer, use_depth: bool) -> torch.Tensor:
    """The head's output offset: the mean target point with depth; without depth the
    mean camera centre (no point is known yet; ACE's choice)."""
    if use_depth:
        return buffer.points.double().mean(dim=0).float()
    return torch.from_numpy(buffer.centres.mean(axis=0)).float()


def new_head(
    buffer: TrainingBuffer, width: int, layers: int, use_depth: bool, seed: int
) -> SceneCoordinateHead:
    """A head sized for the buffer's features, seeded, with the buffer's statistics."""
    features = buffer.features.float()
    head = built_head(features.shape[1], width, layers)
    head.initialise(torch.Generator().manual_seed(seed))
    head.set_statistics(features.mean(dim=0), features.std(dim=0), scene_mean(buffer, use_depth))
    return head


def batch_loss(
    head: SceneCoordinateHead,
    buffer: TrainingBuffer,
    rows: torch.Tensor,
    use_depth: bool,
    tau: float,
    prior_depth: float,
) -> torch.Tensor:
    """The loss of the buffer cells `rows`."""
    predicted = head(buffer.features[rows])
    if use_depth:
        return depth_loss(predicted, buffer.points[rows])
    views = buffer.views[rows]
    loss, _ = reprojection_loss(
        predicted,
        buffer.pixels[rows],
        buffer.intrinsics[views],
        buffer.rotations[views],
        buffer.translations[views],
        tau,
        prior_depth,
    )
    return loss


def train_head(
    buffer: TrainingBuffer,
    head: SceneCoordinateHead,
    settings: TrainingSettings,
    use_depth: bool,
    quiet: bool = True,
) -> list[float]:
    """Train `head` in place on `buffer`; each step's loss, for curves and tests."""
    generator = torch.Generator().manual_seed(settings.seed + 1)  # not the weights' draw
    optimiser = torch.optim.Adam(head.parameters(), lr=settings.lr)
    losses = []
    progress = Progress(settings.steps, "scene coordinates: training the head", quiet=quiet)
    head.train()
    for step in range(settings.steps):
        for group in optimiser.param_groups:
            group["lr"] = settings.lr * learning_rate_factor(step, settings.steps)
        rows = torch.randint(len(buffer), (settings.batch_size,), generator=generator)
        tau = curriculum_threshold(step, settings.steps, settings.tau_start, settings.tau_end)
        loss = batch_loss(head, buffer, rows, use_depth, tau, settings.prior_depth)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
        progress.advance()
    progress.close()
    head.eval()
    if not np.isfinite(losses[-1]):
        # Adam with a far too high refine.lr: say so rather than answer NaN points.
        raise ConfigError(
            f"the scene-coordinate head's loss became {losses[-1]}: refine.lr "
            f"{settings.lr:g} is too high for this scene"
        )
    return losses
