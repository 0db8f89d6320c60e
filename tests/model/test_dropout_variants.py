"""Bayesian PoseNet's dropout placements: what each samples, and what runs once."""

import numpy as np
import pytest
import torch

from relocfw.core.errors import ConfigError
from relocfw.plugins.posenet import PoseNet

TINY = {"input_size": 32, "width": 0.125, "feature_dim": 16}


def tiny_posenet(variant: str, samples: int) -> PoseNet:
    torch.manual_seed(0)
    model = PoseNet(**TINY, mc_samples=samples, dropout_variant=variant)
    return model.eval()


def images(count: int = 3) -> torch.Tensor:
    return torch.rand(count, 3, 32, 32, generator=torch.Generator().manual_seed(1))


class Calls:
    """Batch sizes that reached a module, through a forward hook."""

    def __init__(self, module: torch.nn.Module) -> None:
        self.sizes: list[int] = []
        module.register_forward_hook(lambda _m, args, _out: self.sizes.append(len(args[0])))


@pytest.mark.parametrize("variant", ["kendall", "all"])
def test_sampling_below_the_descriptor_changes_descriptors_and_the_mean_pose(variant):
    model = tiny_posenet(variant, samples=8)
    descriptors = Calls(model.head.descriptor)
    with torch.inference_mode():
        sampled = model(images())
        model.mc_samples = 0
        plain = model(images())
    # The index's descriptor is the dropout-free one...
    assert torch.allclose(sampled.features, plain.features)
    # ...but the samples' descriptors differ from each other (the 8 x 3 pass).
    per_sample = descriptors.sizes
    assert 24 in per_sample
    assert not torch.allclose(sampled.positions, plain.positions)
    assert torch.all(sampled.position_spread > 0)


def test_head_only_sampling_leaves_the_descriptor_and_trunk_alone():
    model = tiny_posenet("head", samples=8)
    descriptors = Calls(model.head.descriptor)
    with torch.inference_mode():
        model(images())
    assert descriptors.sizes == [3]  # one descriptor per image; only the regressor samples


@pytest.mark.parametrize(
    "variant, once, per_sample",
    [("kendall", "inception5b", None), ("all", "inception3a", "inception3b")],
)
def test_the_trunk_below_the_first_dropout_runs_once_per_query(variant, once, per_sample):
    model = tiny_posenet(variant, samples=5)
    stem = Calls(model.trunk.conv1)
    below = Calls(getattr(model.trunk, once))
    above = Calls(getattr(model.trunk, per_sample)) if per_sample else None
    with torch.inference_mode():
        model(images(3))
    assert stem.sizes == [3] and below.sizes == [3]
    if above is not None:
        # One dropout-free pass for the descriptor, then all 5 samples of 3 images.
        assert above.sizes == [3, 15]


def test_samples_are_batched_within_the_memory_bound():
    model = tiny_posenet("kendall", samples=5)
    model.head.images_per_pass = 6
    descriptors = Calls(model.head.descriptor)
    with torch.inference_mode():
        out = model(images(3))
    # 2 samples of 3 images per pass: 6, 6, 3; then the dropout-free 3.
    assert descriptors.sizes == [6, 6, 3, 3]
    assert out.positions.shape == (3, 3) and np.isfinite(out.position_spread.numpy()).all()


@pytest.mark.parametrize("variant, descriptor_sampled", [("head", False), ("kendall", True)])
def test_training_drops_where_the_variant_says(variant, descriptor_sampled):
    model = tiny_posenet(variant, samples=0).train()
    x = images(2)
    torch.manual_seed(3)
    first = model(x).features
    torch.manual_seed(4)
    second = model(x).features
    # head drops after the descriptor; kendall also in the trunk's maps below it.
    assert torch.allclose(first, second) != descriptor_sampled


def test_an_unknown_variant_is_refused():
    with pytest.raises(ConfigError, match="dropout_variant must be one of head, kendall, all"):
        PoseNet(**TINY, dropout_variant="everywhere")


def tiny_efficientnet(variant: str, samples: int):
    lite = pytest.importorskip(
        "relocfw.plugins.efficientnet_lite", reason="relocfw[efficientnet] not installed"
    )
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    torch.manual_seed(0)
    model = lite.EfficientNetLite0(
        input_size=32, feature_dim=16, pretrained=False, mc_samples=samples, dropout_variant=variant
    )
    return model.eval()


@pytest.mark.parametrize("variant", ["kendall", "all"])
def test_efficientnet_variants_sample_below_the_descriptor(variant):
    model = tiny_efficientnet(variant, samples=6)
    stem = Calls(model.trunk._conv_stem)
    second_block = Calls(model.trunk._blocks[1])
    head_conv = Calls(model.trunk._conv_head)
    with torch.inference_mode():
        sampled = model(images(3))
        model.mc_samples = 0
        plain = model(images(3))
    assert torch.allclose(sampled.features, plain.features)
    assert not torch.allclose(sampled.positions, plain.positions)
    assert torch.all(sampled.position_spread > 0)
    # The stem runs once per image in either pass; above the first dropout, all
    # samples run batched: kendall samples only after the head convolution.
    assert stem.sizes == [3, 3]
    if variant == "all":
        # The dropout-free pass for the descriptor, the 6 x 3 samples, the plain run.
        assert second_block.sizes == [3, 18, 3] and head_conv.sizes == [3, 18, 3]
    else:
        assert second_block.sizes == [3, 3] and head_conv.sizes == [3, 3]


def test_efficientnet_head_variant_keeps_the_models_trained_before_variants_existed():
    model = tiny_efficientnet("head", samples=0)
    assert model.key_defaults == {"dropout_variant": "head"}
    model.train()
    x = images(2)
    # Stochastic depth (the package's own) aside, head drops only after the descriptor.
    model.trunk._global_params = model.trunk._global_params._replace(drop_connect_rate=0.0)
    torch.manual_seed(3)
    first = model(x).features
    torch.manual_seed(4)
    second = model(x).features
    assert torch.allclose(first, second)


@pytest.mark.parametrize("training", [False, True])
def test_efficientnet_trunk_split_is_the_packages_own_forward(training):
    model = tiny_efficientnet("head", samples=0).train(training)
    x = images(2)
    torch.manual_seed(5)  # stochastic depth draws the same masks in both
    ours = model.feature_maps(x)
    torch.manual_seed(5)
    theirs = model.trunk.extract_features(x * 2.0 - 1.0)
    assert torch.equal(ours, theirs)
