import pytest
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.plugins.posenet import PoseNet, torchvision_to_posenet_key

# Names and shapes of torchvision's googlenet state_dict, written from its published
# architecture (not from this code), to prove the mapping on an independent layout.
TORCHVISION_SAMPLE = {
    "conv1.conv.weight": (64, 3, 7, 7),
    "conv1.bn.running_var": (64,),
    "conv2.conv.weight": (64, 64, 1, 1),
    "conv3.conv.weight": (192, 64, 3, 3),
    "inception3a.branch1.conv.weight": (64, 192, 1, 1),
    "inception3a.branch2.1.conv.weight": (128, 96, 3, 3),
    "inception3a.branch3.1.conv.weight": (32, 16, 3, 3),
    "inception3a.branch4.1.conv.weight": (32, 192, 1, 1),
    "inception4e.branch2.0.bn.weight": (160,),
    "inception5b.branch4.1.conv.weight": (128, 832, 1, 1),
    "aux1.conv.conv.weight": (128, 512, 1, 1),
    "aux1.fc1.weight": (1024, 2048),
    "aux2.conv.conv.weight": (128, 528, 1, 1),
    "aux2.fc1.bias": (1024,),
}


def tiny(**kwargs):
    torch.manual_seed(0)
    return PoseNet(input_size=32, width=0.125, feature_dim=64, **kwargs)


def test_forward_shapes_and_unit_quaternions():
    model = tiny().eval()
    out = model(torch.rand(3, 3, 32, 32))
    assert out.positions.shape == (3, 3)
    assert out.quaternions.shape == (3, 4)
    assert out.features.shape == (3, 64)
    assert torch.allclose(out.quaternions.norm(dim=1), torch.ones(3), atol=1e-5)
    assert out.auxiliary == ()
    model.train()
    assert len(model(torch.rand(2, 3, 32, 32)).auxiliary) == 2


def test_full_size_descriptor_is_2048():
    model = PoseNet(input_size=64).eval()
    assert model.feature_dim == 2048
    with torch.inference_mode():
        assert model(torch.rand(1, 3, 64, 64)).features.shape == (1, 2048)


def test_position_normalisation_maps_back_to_world():
    model = tiny().eval()
    images = torch.rand(2, 3, 32, 32)
    raw = model(images).positions
    model.set_position_normalisation([10.0, -5.0, 1.0], 2.0)
    world = model(images).positions
    assert torch.allclose(world, raw * 2 + torch.tensor([10.0, -5.0, 1.0]), atol=1e-5)


def torchvision_layout_state(model):
    """A state_dict in torchvision's key layout, with the classifier layers it has too."""
    state = {}
    for key, value in model.state_dict().items():
        if key.startswith("trunk."):
            state[key[len("trunk.") :]] = torch.randn_like(value.float()).to(value.dtype)
        elif key.startswith(("aux1.conv.", "aux1.fc1.", "aux2.conv.", "aux2.fc1.")):
            state[key] = torch.randn_like(value.float()).to(value.dtype)
    state["fc.weight"], state["fc.bias"] = torch.randn(1000, 1024), torch.randn(1000)
    state["aux1.fc2.weight"] = torch.randn(1000, 1024)
    return state


def test_torchvision_key_names_map_to_posenet_parameters():
    ours = PoseNet(input_size=64).state_dict()
    for key, shape in TORCHVISION_SAMPLE.items():
        target = torchvision_to_posenet_key(key)
        assert target in ours, key
        assert tuple(ours[target].shape) == shape, key
    assert torchvision_to_posenet_key("fc.weight") is None
    assert torchvision_to_posenet_key("aux2.fc2.bias") is None


def test_imagenet_weights_load_into_trunk(tmp_path):
    source = PoseNet(input_size=64)
    state = torchvision_layout_state(source)
    path = tmp_path / "googlenet.pth"
    torch.save(state, path)
    model = PoseNet(input_size=64, weights=str(path))
    loaded = model.state_dict()
    assert torch.equal(
        loaded["trunk.inception4c.branch2.1.conv.weight"],
        state["inception4c.branch2.1.conv.weight"],
    )
    assert torch.equal(loaded["aux2.fc1.weight"], state["aux2.fc1.weight"])


def test_bad_weight_files(tmp_path):
    state = torchvision_layout_state(PoseNet(input_size=64))
    del state["inception5b.branch1.conv.weight"]
    path = tmp_path / "partial.pth"
    torch.save(state, path)
    with pytest.raises(DataError, match="lacks 1 GoogLeNet parameters"):
        PoseNet(input_size=64, weights=str(path))
    state["inception5b.branch1.conv.weight"] = torch.zeros(3, 3)
    torch.save(state, path)
    with pytest.raises(DataError, match="has shape"):
        PoseNet(input_size=64, weights=str(path))
    (tmp_path / "junk.pth").write_bytes(b"junk")
    with pytest.raises(DataError, match="cannot read"):
        PoseNet(input_size=64, weights=str(tmp_path / "junk.pth"))
    with pytest.raises(DataError, match="not found"):
        PoseNet(input_size=64, weights=str(tmp_path / "missing.pth"))
    with pytest.raises(ConfigError, match="width=1.0"):
        tiny(weights=str(path))


def test_bad_options():
    with pytest.raises(ConfigError, match="input_size"):
        PoseNet(input_size=8)
    with pytest.raises(ConfigError, match="dropout"):
        PoseNet(input_size=32, dropout=1.0)


def trunk_input(model, images):
    """What the trunk's first convolution receives for `images`."""
    seen = []
    handle = model.trunk.register_forward_pre_hook(lambda _, args: seen.append(args[0]))
    model.eval()
    with torch.no_grad():
        model(images)
    handle.remove()
    return seen[0]


def test_imagenet_googlenet_weights_get_the_input_they_were_trained_on(tmp_path):
    path = tmp_path / "googlenet.pth"
    torch.save(torchvision_layout_state(PoseNet(input_size=64)), path)
    images = torch.rand(2, 3, 64, 64)
    pretrained = PoseNet(input_size=64, weights=str(path))
    # torchvision's GoogLeNet: transform_input maps ImageNet-normalised input to
    # (x - 0.5) / 0.5, i.e. the weights were trained on 2x - 1 of [0, 1] pixels.
    assert torch.allclose(trunk_input(pretrained, images), images * 2 - 1, atol=1e-6)
    scratch = PoseNet(input_size=64)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    assert torch.allclose(trunk_input(scratch, images), (images - mean) / std, atol=1e-6)
    # The normalisation travels with the weights: a model rebuilt without the weights
    # file (as model files and checkpoints do) gets it from the state_dict.
    rebuilt = PoseNet(input_size=64)
    rebuilt.load_state_dict(pretrained.state_dict())
    assert torch.allclose(trunk_input(rebuilt, images), images * 2 - 1, atol=1e-6)
