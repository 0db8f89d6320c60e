"""Test-time sampling of the chosen crop: Monte Carlo dropout and random crops.

Bayesian PoseNet (Kendall & Cipolla, ICRA 2016) answers with the mean of many
stochastic passes and reads their spread as the model's doubt. The pipeline scores
candidate crops with the dropout-free network (the index only ever sees the
dropout-free descriptor, so sampling cannot change which crop a search picks) and
samples only the crop it chose. Two kinds of sample, alone or together:

- Monte Carlo dropout: the backbone's `mc_samples` masks of one window.
- Random crops (`crop_samples`): windows drawn the way training drew them, an
  input-sized window anywhere inside the chosen crop's scaled square. With dropout on
  as well, each window gets one mask of its own, as in the authors' evaluation.

Every query's samples are seeded from the run's seed and the image's fingerprint, so
a query's answer does not depend on which queries ran before it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch

from relocfw.core.geometry import mean_quaternion
from relocfw.core.imaging import Strip
from relocfw.core.interfaces import Backbone
from relocfw.core.multiply_adds import multiply_adds
from relocfw.core.values import Crop


def configured_samples(backbone: Backbone) -> int:
    """The backbone's Monte Carlo dropout samples (0 when it does not sample)."""
    if "mc_samples" not in backbone.test_time_options:
        return 0
    return int(backbone.mc_samples)


def sample_share(backbone: Backbone, device: torch.device) -> float:
    """The share of one dropout-free forward pass's work that each Monte Carlo sample
    adds: the layers from the first dropout up, as network passes count it.

    The backbone's own `sample_share` if it declares one; otherwise measured as the
    multiply-adds (convolutions and linear layers, relocfw.core.multiply_adds) that a
    second sample adds to a one-sample pass of one blank input-sized image, over those
    of a dropout-free pass. The difference is exactly what every further sample reruns,
    whatever the backbone's dropout placement. At 224 px: PoseNet's "head" variant
    reruns the pose regressor (1e-5 of a pass), "kendall" the descriptor layer too
    (0.0014), "all" every block above inception 3a (0.60); EfficientNet-Lite0 4e-5,
    0.0068 and 0.95. 0 for a backbone that does not sample. Deterministic; the
    measurement's dropout draws from a forked stream, so no caller's stream moves.
    """
    if backbone.sample_share is not None:
        return float(backbone.sample_share)
    if "mc_samples" not in backbone.test_time_options:
        return 0.0
    side = backbone.input_size
    blank = torch.zeros(1, 3, side, side, device=device)

    def work(samples: int) -> int:
        with monte_carlo(backbone, samples):
            return multiply_adds(backbone, lambda: backbone(blank))

    with seeded_torch(0, device), torch.inference_mode():
        plain, one, two = work(0), work(1), work(2)
    return (two - one) / plain


@contextmanager
def monte_carlo(backbone: Backbone, samples: int) -> Iterator[None]:
    """Run `backbone` with `samples` dropout masks per image (0: dropout-free)."""
    if "mc_samples" not in backbone.test_time_options:
        yield
        return
    configured = backbone.mc_samples
    backbone.mc_samples = samples
    try:
        yield
    finally:
        backbone.mc_samples = configured


@contextmanager
def seeded_torch(seed: int, device: torch.device) -> Iterator[None]:
    """torch's random streams of the CPU and `device` seeded with `seed` inside,
    restored outside.

    Dropout draws from the default generator of the device it runs on; forking only
    that one (and the CPU's) keeps every stream of the caller (a training run, the
    next query, other GPUs) untouched.
    """
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        with torch.random.fork_rng(devices=[index], device_type="cuda"):
            torch.default_generator.manual_seed(seed)
            torch.cuda.default_generators[index].manual_seed(seed)
            yield
    elif device.type == "mps":
        with torch.random.fork_rng(device_type="mps"):
            torch.default_generator.manual_seed(seed)
            torch.mps.manual_seed(seed)
            yield
    else:
        with torch.random.fork_rng(devices=[]):
            torch.default_generator.manual_seed(seed)
            yield


# Mixed into every sampling stream, so it never repeats a crop search's stream, which
# is drawn from the same run seed and image fingerprint (relocfw.core.interfaces.query_seed).
SAMPLING_STREAM = 0x5A3D1E


def query_streams(seed: int, fingerprint: int) -> tuple[np.random.Generator, int]:
    """One query's random windows' generator and its dropout masks' torch seed, both
    from the run's seed and the image's fingerprint, independent of each other."""
    windows, masks = np.random.SeedSequence([int(seed), int(fingerprint), SAMPLING_STREAM]).spawn(2)
    return np.random.default_rng(windows), int(masks.generate_state(1, np.uint64)[0] >> 1)


def random_windows(
    strip: Strip, crop: Crop, count: int, rng: np.random.Generator
) -> list[tuple[int, int]]:
    """`count` strip corners of input-sized windows drawn uniformly inside `crop`'s
    scaled square: training's random crops (relocfw.model.training), around this crop.

    With crop_scale 1 the window fills the square and every draw is the same window.
    """
    top = round(crop.y * strip.scale)
    left = round(crop.x * strip.scale)
    span = strip.side - strip.input_size
    limit_y = strip.pixels.shape[1] - strip.input_size
    limit_x = strip.pixels.shape[2] - strip.input_size
    offsets = rng.integers(0, span + 1, size=(count, 2))
    return [(min(top + int(dy), limit_y), min(left + int(dx), limit_x)) for dy, dx in offsets]


def combine_samples(
    positions: np.ndarray, quaternions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """[S, 3] positions and [S, 4] quaternions of one query's samples -> mean position,
    mean rotation, position spread (m) and orientation spread (deg), as Monte Carlo
    dropout reports them (sample_statistics, below)."""
    mean_position, mean_quaternion, position_spread, angular_spread = sample_statistics(
        torch.as_tensor(positions, dtype=torch.float64)[:, None],
        torch.as_tensor(quaternions, dtype=torch.float64)[:, None],
    )
    return (
        mean_position[0].numpy(),
        mean_quaternion[0].numpy(),
        float(position_spread[0]),
        float(angular_spread[0]),
    )


def mean_quaternions(samples: torch.Tensor) -> torch.Tensor:
    """[S, B, 4] -> [B, 4]: per batch item, the mean rotation of its S samples (w first,
    w >= 0), in `samples`' dtype and on its device.

    relocfw.core.geometry.mean_quaternion's chordal mean, indifferent to the samples'
    signs, computed in float64 on the CPU: B 4x4 eigenproblems, no slower there than
    torch's own.
    """
    values = samples.detach().to("cpu", torch.float64).numpy()
    means = mean_quaternion(np.swapaxes(values, 0, 1))
    return torch.as_tensor(means, dtype=samples.dtype, device=samples.device)


def sample_statistics(
    positions: torch.Tensor, quaternions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """[S, B, 3] positions and [S, B, 4] unit quaternions of S samples of B images ->
    per image the mean position, the mean rotation, the position spread (m: sqrt of
    the trace of the covariance, one length) and the orientation spread (deg: mean
    angle from the mean rotation).

    Shared by Monte Carlo dropout and test-time crop sampling, so both report the
    same quantities.
    """
    mean_position = positions.mean(0)
    mean_quaternion = mean_quaternions(quaternions)
    position_spread = (positions - mean_position).pow(2).sum(-1).mean(0).sqrt()
    dots = (quaternions * mean_quaternion).sum(-1).abs().clamp(max=1.0)
    angular_spread = torch.rad2deg(2 * torch.acos(dots)).mean(0)
    return mean_position, mean_quaternion, position_spread, angular_spread
