"""The chosen crop's answer from test-time samples (relocfw.core.sampling).

Candidates are scored dropout-free; only the crop a search chose is sampled, once:
its Monte Carlo dropout masks, its random windows, or both.
"""

from __future__ import annotations

import numpy as np
import torch

from relocfw.core.imaging import Strip
from relocfw.core.network_answers import NetworkAnswers
from relocfw.core.sampling import (
    combine_samples,
    configured_samples,
    query_streams,
    random_windows,
    seeded_torch,
)
from relocfw.core.scorer import Scorer
from relocfw.core.values import Crop


def samples_answer(scorer: Scorer, crop_samples: int) -> bool:
    """True when the pipeline answers from samples (dropout masks or random windows)."""
    return crop_samples > 0 or configured_samples(scorer.backbone) > 0


def sampled_answer(
    scorer: Scorer,
    strip: Strip,
    crop: Crop,
    plain: NetworkAnswers,
    crop_samples: int,
    streams: tuple[int, int],
) -> tuple[NetworkAnswers, float]:
    """The chosen crop's answer from its samples, and the network passes they cost.

    Args:
        scorer: the network (its configured `mc_samples` masks per window).
        strip: the query's strip; `crop` its chosen crop.
        plain: the crop's dropout-free answer: its descriptor, the one the index saw,
            stays the answer's descriptor.
        crop_samples: random windows of the crop (0: the crop's own window only).
        streams: (sample seed, the image's fingerprint), which seed the windows and
            the masks, so a query's answer does not depend on the queries before it.
    """
    windows_rng, torch_seed = query_streams(*streams)
    masks = configured_samples(scorer.backbone)
    with seeded_torch(torch_seed, scorer.device):
        if crop_samples == 0:
            sampled = scorer.forward(strip.cut(strip.window(crop))[None], masks)
            return sampled.row(0), scorer.sampled_passes(1, masks)
        corners = random_windows(strip, crop, crop_samples, windows_rng)
        windows = torch.stack([strip.cut(c) for c in corners])
        # With dropout on, one mask per window: every sample is a new crop and mask.
        masks = 1 if masks > 0 else 0
        samples = scorer.forward(windows, masks)
    position, quaternion, position_spread, orientation_spread = combine_samples(
        samples.positions, samples.quaternions
    )
    answer = NetworkAnswers(
        position,
        quaternion,
        plain.features,
        np.float64(position_spread),
        np.float64(orientation_spread),
    )
    return answer, scorer.sampled_passes(len(corners), masks)
