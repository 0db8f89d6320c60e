"""The dropout-variant logic shared by PoseNet and EfficientNet-Lite0
(relocfw.model.dropout_backbone), on a trunk of two convolutions."""

import pytest
import torch
from torch import nn

from relocfw.core.errors import ConfigError
from relocfw.model.dropout_backbone import DropoutBackbone
from relocfw.model.pose_head import PoseHead
from relocfw.plugins.efficientnet_lite import EfficientNetLite0
from relocfw.plugins.posenet import PoseNet


class TwoConvolutions(DropoutBackbone):
    def __init__(self, dropout_variant: str = "head", mc_samples: int = 0) -> None:
        super().__init__(32, 8, 0.5, mc_samples, dropout_variant)
        self.stem = nn.Conv2d(3, 4, 3)
        self.block = nn.Conv2d(4, 6, 3)
        self.head = PoseHead(6, self.feature_dim, self.dropout_rate)
        self.lower_runs = 0

    def normalise(self, images):
        return images - 0.5

    def trunk_lower(self, x):
        self.lower_runs += 1
        return torch.relu(self.stem(x))

    def trunk_upper(self, below, drop=None):
        d = drop or (lambda t: t)
        return (d(torch.relu(self.block(d(below)))),)


def images(count=3):
    return torch.rand(count, 3, 32, 32, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("variant", ["head", "kendall", "all"])
def test_sampling_runs_the_layers_below_the_first_dropout_once(variant):
    torch.manual_seed(0)
    backbone = TwoConvolutions(variant, mc_samples=6).eval()
    with torch.no_grad():
        sampled = backbone(images())
        backbone.mc_samples = 0
        plain = backbone(images())
    assert backbone.lower_runs == 2  # once per call, whatever the samples
    assert sampled.position_spread.shape == (3,) and plain.position_spread is None
    # The index sees the dropout-free descriptor, sampled or not.
    assert torch.allclose(sampled.features, plain.features)
    assert torch.all(sampled.position_spread > 0)


def test_the_descriptor_hooks_agree_with_the_forward_pass():
    backbone = TwoConvolutions("kendall").eval()
    with torch.no_grad():
        maps = backbone.feature_maps(images())
        pooled = backbone.describe_pooled(maps.mean((2, 3)))
        assert torch.allclose(pooled, backbone(images()).features, atol=1e-6)
    assert backbone.shares_strip


def test_kendall_and_all_drop_in_training_and_head_does_not_below_the_descriptor():
    for variant, drops in (("head", False), ("kendall", True), ("all", True)):
        torch.manual_seed(0)
        backbone = TwoConvolutions(variant).train()
        first, second = backbone(images()).features, backbone(images()).features
        assert (not torch.allclose(first, second)) == drops, variant


def test_options_are_checked():
    with pytest.raises(ConfigError, match="dropout_variant"):
        TwoConvolutions("everywhere")
    with pytest.raises(ConfigError, match="mc_samples"):
        TwoConvolutions(mc_samples=-1)


def test_both_plugins_share_it_and_keep_their_own_class_options():
    assert issubclass(PoseNet, DropoutBackbone) and issubclass(EfficientNetLite0, DropoutBackbone)
    assert PoseNet.test_time_options == EfficientNetLite0.test_time_options == ("mc_samples",)
    assert PoseNet.key_defaults == {}
    assert EfficientNetLite0.key_defaults == {"dropout_variant": "head"}
    assert PoseNet.rebuild_overrides == {"weights": None}
    assert EfficientNetLite0.rebuild_overrides == {"pretrained": False}


def test_posenets_state_dict_keeps_its_names():
    # Cached checkpoints and saved model files load by these names.
    keys = PoseNet(input_size=32, width=0.125, feature_dim=8).state_dict().keys()
    assert {k.split(".")[0] for k in keys} == {
        "position_mean", "position_scale", "crop_scale", "mean", "std",
        "trunk", "aux1", "aux2", "head",
    }  # fmt: skip
    assert "head.descriptor.weight" in keys and "trunk.inception5b.branch1.conv.weight" in keys
    assert "aux1.pose.orientation.bias" in keys
