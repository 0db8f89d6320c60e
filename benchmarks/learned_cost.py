"""What the learned relocalizers of methods=learned cost: PoseNet (EfficientNet-Lite0),
the hourglass (the same encoder plus a decoder) and the sequence model on top of either.

At the real_cpu_quick geometry (96-pixel input, batches of 32), measured round robin
in one process so that a slow moment of the machine falls on every method alike:

- training step: forward, PoseNet's loss, backward and an Adam step on one fixed
  batch (ms per step; the preset trains 600 steps);
- query: one centre crop through the network in inference mode (ms; what the
  centre-crop row costs per query beside image decoding);
- sequence model: training the LSTM on a map of `--map-images` descriptors (seconds,
  refine=sequence's settings but the window, `--window`) and one query's refine() on
  a full window (ms);
- memory: parameters (millions) and their float32 size (MB).

Prints a table, writes JSON.

    .venv/bin/python benchmarks/learned_cost.py --rounds 5 --window 10
"""

from __future__ import annotations

import argparse
import inspect
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from common import device_name, write_json  # benchmarks/, the script's own folder

from relocfw.core.refinement import MapImage, RefineQuery
from relocfw.core.values import Pose
from relocfw.model.loss import FixedWeighting, posenet_loss
from relocfw.plugins.efficientnet_lite import EfficientNetLite0
from relocfw.plugins.hourglass import Hourglass
from relocfw.plugins.sequence_refiner import SequenceRefiner

NETWORKS: dict[str, Callable[[int], torch.nn.Module]] = {
    "PoseNet (EfficientNet-Lite0)": lambda size: EfficientNetLite0(input_size=size),
    "Hourglass": lambda size: Hourglass(input_size=size),
}


def timed(run: Callable[[], object]) -> float:
    started = time.perf_counter()
    run()
    return time.perf_counter() - started


def training_step(network: torch.nn.Module, batch: int, size: int) -> Callable[[], None]:
    """One forward + loss + backward + Adam step on a fixed batch, as training runs it."""
    images = torch.rand(batch, 3, size, size).contiguous(memory_format=torch.channels_last)
    positions = torch.randn(batch, 3)
    quaternions = torch.nn.functional.normalize(torch.randn(batch, 4), dim=1)
    weighting = FixedWeighting(1.0)  # the preset's train.beta
    optimizer = torch.optim.Adam(network.parameters(), lr=3e-4)

    def step() -> None:
        network.train()
        loss = posenet_loss(network(images), positions, quaternions, weighting)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        loss.item()

    return step


def query(network: torch.nn.Module, size: int) -> Callable[[], None]:
    image = torch.rand(1, 3, size, size).contiguous(memory_format=torch.channels_last)

    def run() -> None:
        network.eval()
        with torch.inference_mode():
            network(image)

    return run


def sequence_costs(feature_dim: int, map_images: int, window: int, steps: int) -> dict[str, float]:
    """Seconds to fit refine=sequence (its defaults, `steps` Adam steps) on a map of
    random descriptors and poses in 100-frame recordings, and ms per query on a full
    window (the cost does not depend on what the descriptors hold)."""
    rng = np.random.default_rng(0)
    views = [
        MapImage(
            f"seq-{i // 100:02d}/frame-{i % 100:06d}",
            np.zeros((4, 4, 3), np.uint8),
            Pose(rng.normal(size=3), np.array([1.0, 0, 0, 0])),
        )
        for i in range(map_images)
    ]
    descriptors = rng.normal(size=(map_images, feature_dim))
    refiner = SequenceRefiner(window=window, steps=steps)
    fit_seconds = timed(lambda: refiner.fit(views, descriptors, quiet=True))
    queries = [
        RefineQuery(np.zeros((4, 4, 3), np.uint8), views[0].pose, d, name=f"q/{i:06d}")
        for i, d in enumerate(rng.normal(size=(window + 20, feature_dim)))
    ]
    for q in queries[:window]:  # fill the window first
        refiner.refine(q)
    per_query = [timed(lambda q=q: refiner.refine(q)) for q in queries[window:]]
    return {"fit_s": fit_seconds, "query_ms": 1000 * statistics.median(per_query)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=96, help="network input (real_cpu_quick: 96)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--rounds", type=int, default=5, help="round-robin rounds")
    parser.add_argument("--steps", type=int, default=3, help="training steps timed per round")
    parser.add_argument("--queries", type=int, default=20, help="queries timed per round")
    parser.add_argument("--map-images", type=int, default=400)
    # The sequence model's defaults are refine=sequence's own, read from its constructor.
    refiner_defaults = inspect.signature(SequenceRefiner).parameters
    parser.add_argument(
        "--window", type=int, default=refiner_defaults["window"].default, help="refine.window"
    )
    parser.add_argument(
        "--sequence-steps", type=int, default=refiner_defaults["steps"].default, help="refine.steps"
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/learned_cost.json"))
    args = parser.parse_args()
    torch.manual_seed(0)
    networks = {name: make(args.size) for name, make in NETWORKS.items()}
    for network in networks.values():
        network.to(memory_format=torch.channels_last)
    steps = {n: training_step(net, args.batch_size, args.size) for n, net in networks.items()}
    queries = {n: query(net, args.size) for n, net in networks.items()}
    for name in networks:  # warm-up: first calls pay for allocations and kernel choice
        steps[name]()
        queries[name]()
    step_ms = {name: [] for name in networks}
    query_ms = {name: [] for name in networks}
    for _ in range(args.rounds):
        for name in networks:
            step_ms[name] += [1000 * timed(steps[name]) for _ in range(args.steps)]
            query_ms[name] += [1000 * timed(queries[name]) for _ in range(args.queries)]
    rows = []
    for name, network in networks.items():
        parameters = sum(p.numel() for p in network.parameters())
        rows.append(
            {
                "method": name,
                "train_step_ms": statistics.median(step_ms[name]),
                "query_ms": statistics.median(query_ms[name]),
                "parameters_millions": parameters / 1e6,
                "parameters_mb": parameters * 4 / 2**20,
                "feature_dim": int(network.feature_dim),
            }
        )
    sequence = sequence_costs(
        int(rows[0]["feature_dim"]), args.map_images, args.window, args.sequence_steps
    )
    report = {
        "machine": platform.processor() or platform.machine(),
        "device": device_name("cpu"),
        "torch_threads": torch.get_num_threads(),
        "settings": vars(args) | {"out": str(args.out)},
        "rows": rows,
        "sequence_model": sequence,
    }
    print(f"{'method':32} {'train step (ms)':>16} {'query (ms)':>11} {'params (M)':>11}")
    for row in rows:
        print(
            f"{row['method']:32} {row['train_step_ms']:16.0f} {row['query_ms']:11.1f} "
            f"{row['parameters_millions']:11.2f}"
        )
    print(
        f"sequence model: fit {sequence['fit_s']:.1f} s on {args.map_images} map images, "
        f"{sequence['query_ms']:.2f} ms per query ({args.window}-frame window)"
    )
    write_json(report, args.out)


if __name__ == "__main__":
    main()
