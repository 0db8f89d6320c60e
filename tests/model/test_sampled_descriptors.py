"""What each Monte Carlo sample sees: its own descriptor below the regressor for the
kendall and all variants, the same descriptor for head (where only the regressor's
dropout samples). Positions that differ are not enough: head dropout alone gives that.
"""

import pytest
import torch

from relocfw.plugins.posenet import PoseNet

SAMPLES, IMAGES = 6, 3


def images() -> torch.Tensor:
    return torch.rand(IMAGES, 3, 32, 32, generator=torch.Generator().manual_seed(1))


def with_unit_scale(model):
    """`model` with batch norm's statistics set from one batch, as training would.

    A freshly initialised trunk's maps shrink layer by layer (to ~1e-5 at PoseNet's
    inception 5b, ~1e-10 at EfficientNet's last maps), and so would any difference
    dropout makes; the statistics bring every layer back to unit scale.
    """
    for layer in model.modules():
        if isinstance(layer, torch.nn.BatchNorm2d):
            layer.momentum = None  # a plain average: one batch sets the statistics
    with torch.no_grad():
        model.train()(images())
    return model


def posenet(variant: str):
    torch.manual_seed(0)
    return with_unit_scale(
        PoseNet(
            input_size=32, width=0.125, feature_dim=64, mc_samples=SAMPLES, dropout_variant=variant
        )
    )


def efficientnet(variant: str):
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    from relocfw.plugins.efficientnet_lite import EfficientNetLite0

    torch.manual_seed(0)
    return with_unit_scale(
        EfficientNetLite0(
            input_size=32,
            feature_dim=64,
            pretrained=False,
            mc_samples=SAMPLES,
            dropout_variant=variant,
        )
    )


def per_sample_descriptors(backbone) -> tuple[torch.Tensor, torch.Tensor]:
    """[S, B, D] the descriptors PoseHead.sampled got for its samples, and [B, D] the
    dropout-free descriptors of the same images."""
    head = backbone.head
    seen = []
    sampled = head.sampled

    def spy(descriptors, features, *args):
        seen.append((descriptors.clone(), features.clone()))
        return sampled(descriptors, features, *args)

    head.sampled = spy
    with torch.inference_mode():
        backbone.eval()(images())
    (descriptors, features), *more = seen
    assert not more  # one sampling per forward pass
    return descriptors.view(SAMPLES, IMAGES, -1), features


MAKERS = [posenet, efficientnet]


@pytest.mark.parametrize("variant", ["kendall", "all"])
@pytest.mark.parametrize("make", MAKERS, ids=["posenet", "efficientnet"])
def test_every_sample_of_a_deep_variant_has_a_descriptor_of_its_own(make, variant):
    descriptors, features = per_sample_descriptors(make(variant))
    length = features.norm(dim=1)  # [B] of the dropout-free descriptors
    # Each sample stands apart from the samples' mean and from the dropout-free
    # descriptor, by far more than rounding: copies (head dropout only) would be 0.
    from_mean = (descriptors - descriptors.mean(0)).norm(dim=2)  # [S, B]
    from_clean = (descriptors - features).norm(dim=2)
    assert torch.all(from_mean > 0.05 * length), from_mean / length
    assert torch.all(from_clean > 0.05 * length), from_clean / length


@pytest.mark.parametrize("make", MAKERS, ids=["posenet", "efficientnet"])
def test_head_dropout_samples_copies_of_the_dropout_free_descriptor(make):
    descriptors, features = per_sample_descriptors(make("head"))
    assert torch.equal(descriptors, features.expand(SAMPLES, -1, -1))
