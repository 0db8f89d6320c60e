"""Training images per second against the bare forward + backward rate of the same model.

Is the data side (cutting random crops from the in-memory strips, assembling the
batch) holding training back? Both rates use the paper's geometry (640 x 480 views,
224-pixel GoogLeNet PoseNet input) and the same batch size, loss and optimiser:

- bare: one batch made up front, then forward, loss, backward and step in a loop;
- train_backbone: the real training loop, drawing and cutting a new batch every step.

Prints a table, writes JSON.

    .venv/bin/python benchmarks/training_throughput.py --steps 6 --rounds 2 --batch-size 16
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch
from common import device_name, render_views, write_json  # benchmarks/, the script's own folder

from relocfw.core.imaging import to_network_input
from relocfw.model.loss import posenet_loss
from relocfw.model.training import (
    TrainingImages,
    TrainSettings,
    make_optimizer,
    make_weighting,
    train_backbone,
)
from relocfw.plugins.posenet import PoseNet


def bare_rate(
    backbone: PoseNet, data: TrainingImages, settings: TrainSettings, steps: int, device: str
) -> float:
    """Images per second of forward + loss + backward + step on one fixed batch."""
    generator = torch.Generator().manual_seed(0)
    indices = torch.randint(len(data), (settings.batch_size,), generator=generator)
    images, positions, quaternions = data.batch(indices, generator, settings.random_crops)
    inputs = to_network_input(images.to(device))
    positions, quaternions = positions.to(device), quaternions.to(device)
    backbone.to(device)
    if backbone.channels_last:  # as train_backbone runs it
        backbone.to(memory_format=torch.channels_last)
        inputs = inputs.contiguous(memory_format=torch.channels_last)
    weighting = make_weighting(settings).to(device)
    optimizer = make_optimizer([backbone, weighting], settings)
    backbone.train()

    def step() -> None:
        loss = posenet_loss(backbone(inputs), positions, quaternions, weighting)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        loss.item()  # the training loop reads every loss too

    step()  # warm-up
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * settings.batch_size / (time.perf_counter() - start)


def loop_rate(
    backbone: PoseNet, data: TrainingImages, settings: TrainSettings, steps: int, device: str
) -> float:
    """Images per second of `train_backbone` itself, new random crops every step."""
    warm = TrainSettings(**{**settings.__dict__, "iterations": 1})
    train_backbone(backbone, data, warm, device=device, quiet=True)  # warm-up; builds strips
    timed = TrainSettings(**{**settings.__dict__, "iterations": steps})
    start = time.perf_counter()
    train_backbone(backbone, data, timed, device=device, quiet=True)
    return steps * settings.batch_size / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--images", type=int, default=48)
    parser.add_argument("--input-size", type=int, default=224)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/training_throughput.json")
    )
    args = parser.parse_args()
    images, poses = render_views(args.images, 0)
    data = TrainingImages(images, poses, args.input_size)
    settings = TrainSettings(batch_size=args.batch_size, lr=1e-3, beta=10.0, seed=0)
    torch.manual_seed(0)
    backbone = PoseNet(input_size=args.input_size)
    # Alternated rounds, best of each: a busy moment on the machine should not decide.
    bare, loop = 0.0, 0.0
    for _ in range(args.rounds):
        loop = max(loop, loop_rate(backbone, data, settings, args.steps, args.device))
        bare = max(bare, bare_rate(backbone, data, settings, args.steps, args.device))
    report = {
        "geometry": {"image": [640, 480], "input": args.input_size},
        "batch_size": args.batch_size,
        "steps": args.steps,
        "rounds": args.rounds,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "device": device_name(args.device),
        "bare_images_per_second": bare,
        "train_images_per_second": loop,
        "train_share_of_bare": loop / bare,
    }
    print(f"{'':<24} {'images/s':>9}")
    print(f"{'bare forward+backward':<24} {bare:>9.2f}")
    print(f"{'train_backbone':<24} {loop:>9.2f}")
    print(f"train_backbone reaches {loop / bare:.1%} of the bare rate")
    write_json(report, args.out)


if __name__ == "__main__":
    main()
