"""Monte Carlo dropout's cost in network passes: what every sample reruns counts."""

import numpy as np
import pytest
import torch
from torch import nn

from relocfw import Relocalizer
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet

SAMPLES = 40


def rgb(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (36, 48, 3), dtype=np.uint8)


def posenet(variant: str, samples: int = SAMPLES) -> PoseNet:
    torch.manual_seed(0)
    return PoseNet(
        input_size=32, width=0.125, feature_dim=16, mc_samples=samples, dropout_variant=variant
    )


def efficientnet(variant: str, samples: int = SAMPLES):
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    from relocfw.plugins.efficientnet_lite import EfficientNetLite0

    torch.manual_seed(0)
    return EfficientNetLite0(
        input_size=32, feature_dim=16, pretrained=False, mc_samples=samples, dropout_variant=variant
    )


def centre_crop_passes(backbone) -> float:
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    relocalizer.fit([rgb(seed) for seed in range(3)])
    return relocalizer.localize(rgb(7)).network_passes


def test_sampling_above_the_trunk_costs_more_than_one_pass():
    # One plain pass of the centre crop, one sampled pass of it: about 2 with head
    # dropout, whose samples rerun only the regressor.
    assert centre_crop_passes(posenet("head")) == pytest.approx(2.0, abs=0.01)
    # All 40 samples rerun every inception block above 3a: many passes' worth.
    assert centre_crop_passes(posenet("all")) > 10
    # Kendall's samples rerun only the descriptor layer and the regressor: a small
    # share (about 0.3% of this tiny net, 0.14% of a full GoogLeNet), 40 times.
    assert centre_crop_passes(posenet("kendall")) > 2.05


def below_first_dropout(backbone, variant: str, images: torch.Tensor) -> int:
    """Multiply-adds of the layers that run once per query whatever the samples: the
    trunk under the first dropout (counted from its parts, not from sampling)."""
    from relocfw.core.multiply_adds import multiply_adds

    if variant == "all":
        normalised = backbone.trunk if isinstance(backbone, PoseNet) else backbone
        return multiply_adds(backbone, lambda: normalised.lower(images))
    # kendall: the whole trunk; head: the trunk and the descriptor layer.
    head = backbone.head
    above = [head.regressor] if variant == "head" else [head.descriptor, head.regressor]
    everything = multiply_adds(backbone, lambda: backbone(images))
    return everything - sum(multiply_adds(layer, lambda: backbone(images)) for layer in above)


@pytest.mark.parametrize("variant", ["head", "kendall", "all"])
@pytest.mark.parametrize("make", [posenet, efficientnet], ids=["posenet", "efficientnet"])
def test_passes_are_one_plus_samples_times_the_share_above_the_first_dropout(make, variant):
    from relocfw.core.multiply_adds import multiply_adds
    from relocfw.core.sampling import sample_share

    backbone = make(variant).eval()
    blank = torch.zeros(1, 3, 32, 32)
    with torch.inference_mode():
        backbone.mc_samples = 0
        plain = multiply_adds(backbone, lambda: backbone(blank))
        below = below_first_dropout(backbone, variant, blank)
        backbone.mc_samples = SAMPLES
    expected = (plain - below) / plain  # the formula, from the layers themselves
    assert sample_share(backbone, torch.device("cpu")) == pytest.approx(expected, rel=1e-9)
    assert 0 < expected < 1
    # The centre crop's plain pass, then the sampled pass: once, plus 40 shares.
    assert centre_crop_passes(backbone) == pytest.approx(2 + SAMPLES * expected)


def test_a_backbone_that_declares_its_share_is_taken_at_its_word():
    from relocfw.core.sampling import sample_share

    backbone = posenet("all")
    backbone.sample_share = 0.5
    assert sample_share(backbone, torch.device("cpu")) == 0.5
    assert centre_crop_passes(backbone) == pytest.approx(2 + SAMPLES * 0.5)


def test_measuring_the_share_leaves_the_callers_random_stream_and_samples_alone():
    from relocfw.core.sampling import sample_share

    backbone = posenet("kendall", samples=7).eval()
    torch.manual_seed(3)
    expected = torch.rand(2)
    torch.manual_seed(3)
    sample_share(backbone, torch.device("cpu"))
    assert torch.equal(torch.rand(2), expected) and backbone.mc_samples == 7


def test_multiply_adds_count_convolutions_and_linear_layers_as_run():
    from relocfw.core.multiply_adds import multiply_adds

    network = nn.Sequential(nn.Conv2d(3, 4, 3, padding=1, groups=1), nn.Flatten(), nn.Linear(64, 5))
    images = torch.zeros(2, 3, 4, 4)
    # Conv: 2 x 4 x 4 x 4 outputs, 3 x 3 x 3 each; linear: 2 x 5 outputs, 64 each.
    assert multiply_adds(network, lambda: network(images)) == 2 * 64 * 27 + 2 * 5 * 64
    grouped = nn.Conv2d(4, 4, 1, groups=2)
    assert multiply_adds(grouped, lambda: grouped(torch.zeros(1, 4, 2, 2))) == 16 * 2


def test_a_transposed_convolution_counts_its_input_cells_times_its_kernel():
    from relocfw.core.multiply_adds import multiply_adds

    # Each of 2 x 3 x 5 x 5 input values meets 4 output channels x 4 x 4 taps: the
    # work is the same spread however much the stride enlarges the output.
    for stride in (1, 2):
        up = nn.ConvTranspose2d(3, 4, 4, stride=stride)
        assert multiply_adds(up, lambda up=up: up(torch.zeros(2, 3, 5, 5))) == 2 * 3 * 25 * 4 * 16
