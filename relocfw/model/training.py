"""Training a backbone on posed images, resumable and reusable through its checkpoint."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from relocfw.core.atomic_files import remove_stale_temporaries
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import Strip, to_network_input
from relocfw.core.interfaces import Backbone
from relocfw.core.options import integer_at_least, real_number
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.model.checkpoints import CHECKPOINT_FORMAT, load_checkpoint, save_atomic
from relocfw.model.distributed import (
    World,
    data_parallel,
    gather_rng_states,
    restore_own_rng_state,
)
from relocfw.model.loss import FixedWeighting, LearnedWeighting, posenet_loss

# PoseNet's training crops: 224 of a 256-pixel short side. On the validation splits of
# benchmarks/training_crops.py it beat crops of the whole short side (README).
POSENET_CROP_SCALE = 256 / 224
# What one unit of position error is in the loss (TrainSettings.position_frame).
POSITION_FRAMES = ("normalised", "world")


@dataclass(frozen=True)
class TrainSettings:
    """How to train; the paper's values are in conf/preset/paper.yaml.

    Attributes:
        iterations: optimiser steps.
        batch_size: images per step.
        optimizer: "sgd" (paper, with momentum) or "adam".
        lr: learning rate.
        lr_schedule: "constant" (paper) or "cosine" (decays to 1% by the end).
        momentum: SGD momentum.
        weight_decay: L2 penalty.
        loss: "fixed" (paper: position + beta x orientation) or "learned" (Kendall &
            Cipolla 2017 homoscedastic weighting).
        beta: weight of the quaternion error against the position error (fixed), the
            latter in units of `position_frame`.
        position_frame: what one unit of position error is in the loss. "normalised":
            the spread of the training positions, the frame the network regresses in,
            so beta means the same at any scene scale (metres, or a COLMAP model's
            arbitrary unit); every preset but the paper's uses it. "world" (the
            paper's, so the default with its beta 250): one unit of the poses,
            PoseNet's beta in metres (120-750 indoors); only right for metric scenes.
        learned_init: initial (s_x, s_q) of the learned weighting.
        auxiliary_weights: loss weights of the two auxiliary heads.
        random_crops: train on a random square crop of each image (paper), not the centre.
        crop_scale: the image's short side is scaled to crop_scale x the network input
            before a random input-sized crop is cut. 1.0: the crop is the whole short
            side and moves along the long axis only. 256/224 (1.142857, the default):
            PoseNet's scheme (224 crops of the image at a 256-pixel short side), so
            crops also move along the short axis and see 87.5% of it. Training records
            it in the backbone, and queries then show the network the central
            1/crop_scale of each crop, as PoseNet tests on the centre 224 crop.
        checkpoint_every: steps between resumable checkpoints.
        seed: initialisation and batch order.
    """

    iterations: int = 30000
    batch_size: int = 75
    optimizer: str = "sgd"
    lr: float = 1e-5
    lr_schedule: str = "constant"
    momentum: float = 0.9
    weight_decay: float = 0.0
    loss: str = "fixed"
    beta: float = 250.0
    position_frame: str = "world"
    learned_init: tuple[float, float] = (0.0, -3.0)
    auxiliary_weights: tuple[float, float] = (0.3, 0.3)
    random_crops: bool = True
    crop_scale: float = POSENET_CROP_SCALE
    checkpoint_every: int = 500
    seed: int = 0

    def validate(self) -> None:
        for key in ("iterations", "batch_size", "checkpoint_every"):
            integer_at_least(f"train.{key}", getattr(self, key), 1)
        for key in ("lr", "momentum", "weight_decay", "beta", "crop_scale"):
            real_number(f"train.{key}", getattr(self, key))
        if len(self.auxiliary_weights) != 2:
            raise ConfigError("train.auxiliary_weights must hold two numbers (aux1, aux2)")
        for weight in self.auxiliary_weights:
            real_number("train.auxiliary_weights", weight)
        if self.loss not in ("fixed", "learned"):
            raise ConfigError(f"train.loss must be 'fixed' or 'learned', got {self.loss!r}")
        if len(self.learned_init) != 2:
            raise ConfigError("train.learned_init must hold two numbers (s_x, s_q)")
        if self.position_frame not in POSITION_FRAMES:
            raise ConfigError(
                f"train.position_frame must be one of {', '.join(POSITION_FRAMES)}, "
                f"got {self.position_frame!r}"
            )
        if self.optimizer not in ("sgd", "adam"):
            raise ConfigError(f"train.optimizer must be 'sgd' or 'adam', got {self.optimizer!r}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ConfigError(
                f"train.lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}"
            )
        if not self.lr > 0:
            raise ConfigError(f"train.lr must be positive, got {self.lr}")
        if self.beta < 0:
            raise ConfigError(f"train.beta must be >= 0, got {self.beta}")
        if not 1.0 <= self.crop_scale <= 4.0:
            raise ConfigError(
                f"train.crop_scale must be in [1, 4] (short side over the network input), "
                f"got {self.crop_scale}"
            )


@dataclass(frozen=True)
class TrainingRun:
    """What `train_backbone` did: every step's loss, and whether it only loaded a model."""

    losses: list[float]
    reused: bool
    resumed_from: int = 0  # the step an interrupted run was continued from, 0 if none
    # Per step: "loss", "lr", each head's weighted loss, the main head's errors and,
    # with train.loss=learned, "s_position" and "s_orientation" (training curves).
    history: dict[str, list[float]] = field(default_factory=dict)


class TrainingImages:
    """Training strips in memory, cut into random square crops batch by batch.

    Strips are scaled to the network input once, so a batch is a few tensor slices:
    the data side costs microseconds against the network's milliseconds.
    """

    def __init__(
        self,
        images: Sequence[np.ndarray],
        poses: Sequence[Pose],
        input_size: int,
        crop_scale: float = POSENET_CROP_SCALE,
    ):
        if len(images) == 0:
            raise DataError("the training split is empty")
        self.images = images
        self.crop_scale = float(crop_scale)
        self.positions = torch.tensor(np.stack([p.position for p in poses]), dtype=torch.float32)
        self.quaternions = torch.tensor(
            np.stack([p.quaternion for p in poses]), dtype=torch.float32
        )
        self.input_size = input_size

    @cached_property
    def strips(self) -> list[Strip]:
        # Built on the first batch, not up front: a reused checkpoint never needs them.
        # Strips at crop_scale x the input: windows of input size then see 1/crop_scale
        # of the short side (TrainSettings.crop_scale).
        return [Strip(image, self.input_size, self.crop_scale) for image in self.images]

    def __len__(self) -> int:
        return len(self.images)

    def batch(
        self, indices: torch.Tensor, generator: torch.Generator, random_crops: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        crops = []
        for i in indices.tolist():
            pixels = self.strips[i].pixels
            span_y = pixels.shape[1] - self.input_size
            span_x = pixels.shape[2] - self.input_size
            if random_crops:
                y = int(torch.randint(span_y + 1, (), generator=generator))
                x = int(torch.randint(span_x + 1, (), generator=generator))
            else:
                y, x = span_y // 2, span_x // 2
            crops.append(pixels[:, y : y + self.input_size, x : x + self.input_size])
        return torch.stack(crops), self.positions[indices], self.quaternions[indices]


def learning_rate(settings: TrainSettings, step: int) -> float:
    if settings.lr_schedule == "constant":
        return settings.lr
    progress = step / max(1, settings.iterations)
    return settings.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * progress)))


def make_weighting(settings: TrainSettings) -> torch.nn.Module:
    if settings.loss == "learned":
        return LearnedWeighting(*settings.learned_init)
    return FixedWeighting(settings.beta)


def make_optimizer(
    modules: Sequence[torch.nn.Module], settings: TrainSettings
) -> torch.optim.Optimizer:
    parameters = [p for module in modules for p in module.parameters()]
    if settings.optimizer == "adam":
        return torch.optim.Adam(parameters, lr=settings.lr, weight_decay=settings.weight_decay)
    return torch.optim.SGD(
        parameters,
        lr=settings.lr,
        momentum=settings.momentum,
        weight_decay=settings.weight_decay,
    )


def train_backbone(
    backbone: Backbone,
    data: TrainingImages,
    settings: TrainSettings,
    checkpoint: Path | None = None,
    key: str = "",
    device: str | torch.device = "cpu",
    quiet: bool = False,
    world: World | None = None,
    log_dir: Path | None = None,
) -> TrainingRun:
    """Train `backbone` in place; returns the loss of every step.

    `log_dir`: also write every step's losses, learning rate and learned loss weights
    there as TensorBoard events (needs the `tensorboard` package).

    With a checkpoint path: a complete checkpoint with the same key is loaded instead
    of training (the same model asked for again); an incomplete one is resumed; a new
    one is written every `checkpoint_every` steps and at the end, atomically.

    With a `world` (torch.distributed initialised, e.g. under torchrun), this process
    trains on its share of every global batch under DistributedDataParallel; rank 0
    alone writes checkpoints and shows progress. Losses are global-batch means. Each
    process draws its own dropout masks (torch seeded from the seed and its rank);
    checkpoints keep every process's random streams, so resuming needs as many
    processes as the interrupted run had.
    """
    settings.validate()
    if abs(data.crop_scale - settings.crop_scale) > 1e-6:
        raise ConfigError(
            f"the training images were cut with crop_scale={data.crop_scale:.6g} but "
            f"train.crop_scale={settings.crop_scale:.6g}; build TrainingImages with the "
            "settings' crop_scale"
        )
    if world is not None:
        world.check_batch(settings.batch_size)
        quiet = quiet or not world.is_main
    writes = world is None or world.is_main
    device = torch.device(device)
    # Batches come from `generator`, the same on every process; torch's own streams
    # (dropout) are per process, or all ranks would drop the same units.
    torch.manual_seed(settings.seed if world is None else world.torch_seed(settings.seed))
    generator = torch.Generator().manual_seed(settings.seed)
    positions = data.positions.numpy()
    backbone.set_position_normalisation(
        positions.mean(axis=0), float(max(positions.std(axis=0).mean(), 1e-3))
    )
    backbone.set_crop_scale(data.crop_scale)
    position_unit = (
        float(backbone.position_scale) if settings.position_frame == "normalised" else 1.0
    )
    # Channels-last trains GoogLeNet about 1.6x faster on CPU (benchmarks/).
    memory_format = torch.channels_last if backbone.channels_last else torch.contiguous_format
    backbone.to(device=device, memory_format=memory_format)
    weighting = make_weighting(settings).to(device)
    optimizer = make_optimizer([backbone, weighting], settings)
    losses: list[float] = []
    history: dict[str, list[float]] = {}
    step = resumed_from = 0
    if checkpoint is not None and writes:
        remove_stale_temporaries(checkpoint)
    if checkpoint is not None and Path(checkpoint).is_file():
        state = load_checkpoint(checkpoint)
        if state.get("key") != key:
            raise DataError(f"{checkpoint} belongs to other settings (key {state.get('key')})")
        try:
            backbone.load_state_dict(state["model"])
            weighting.load_state_dict(state["weighting"])
        except (RuntimeError, KeyError) as error:
            raise DataError(
                f"{checkpoint} does not fit this backbone ({str(error).splitlines()[0]}); "
                "delete it or choose another cache_dir"
            ) from error
        if state["complete"]:
            return TrainingRun(
                list(state["losses"]), reused=True, history=dict(state.get("history", {}))
            )
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["generator"])
        # Every process's dropout masks continue as they would have.
        restore_own_rng_state(state["rng"], world, device, checkpoint)
        step, losses = state["iteration"], list(state["losses"])
        history = {k: list(v) for k, v in state.get("history", {}).items()}
        resumed_from = step

    def save(complete: bool) -> None:
        if checkpoint is None:
            return
        rng = gather_rng_states(world, device)  # a collective: every process takes part
        if writes:
            payload = {
                "format": CHECKPOINT_FORMAT,
                "key": key,
                "complete": complete,
                "iteration": step,
                "model": backbone.state_dict(),
                "weighting": weighting.state_dict(),
                "optimizer": optimizer.state_dict(),
                "generator": generator.get_state(),
                "rng": rng,  # per rank: each process's CPU (and GPU) stream
                "losses": losses,
                "history": history,
                "settings": asdict(settings),
            }
            save_atomic(payload, checkpoint)

    model = data_parallel(backbone, world, device)
    events = tensorboard_writer(log_dir) if log_dir is not None and writes else None
    backbone.train()
    progress = Progress(settings.iterations, "training", quiet=quiet)
    progress.advance(step)
    while step < settings.iterations:
        indices = torch.randint(len(data), (settings.batch_size,), generator=generator)
        batch = data.batch(indices, generator, settings.random_crops)
        if world is not None:
            batch = tuple(world.share(part) for part in batch)
        images, true_positions, true_quaternions = batch
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(settings, step)
        inputs = to_network_input(images.to(device)).contiguous(memory_format=memory_format)
        output = model(inputs)
        parts: dict[str, torch.Tensor] = {}
        loss = posenet_loss(
            output,
            true_positions.to(device),
            true_quaternions.to(device),
            weighting,
            settings.auxiliary_weights,
            parts,
            position_unit,
        )
        batch_loss = loss if world is None else world.mean(loss)
        if not torch.isfinite(batch_loss):
            raise DataError(
                f"training diverged at step {step} (loss {batch_loss.item()}); lower train.lr"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if world is not None:
            world.average_gradients(weighting)
        optimizer.step()
        step += 1
        losses.append(batch_loss.item())
        record = {"loss": losses[-1], "lr": optimizer.param_groups[0]["lr"]}
        record |= {name: float(value) for name, value in parts.items()}
        record |= {name: float(p.detach()) for name, p in weighting.named_parameters()}
        for name, value in record.items():
            history.setdefault(name, []).append(value)
            if events is not None:
                events.add_scalar(f"train/{name}", value, step)
        recent = float(np.mean(losses[-20:]))
        progress.advance(1, suffix=f"loss {recent:.3f}")
        if step % settings.checkpoint_every == 0 and step < settings.iterations:
            save(complete=False)
    progress.close()
    if events is not None:
        events.close()
    backbone.eval()
    save(complete=True)
    if world is not None:
        world.barrier()  # the checkpoint is complete before any process moves on
    return TrainingRun(losses, reused=False, resumed_from=resumed_from, history=history)


def tensorboard_writer(log_dir: Path):  # noqa: ANN201 - torch's SummaryWriter, imported late
    """A TensorBoard event writer in `log_dir`; ConfigError without the package."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as error:
        raise ConfigError(
            "train.log=tensorboard needs the tensorboard package: "
            'pip install "relocfw[tensorboard]"'
        ) from error
    return SummaryWriter(log_dir=str(log_dir))
