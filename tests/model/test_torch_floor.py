"""No torch file is read under a torch whose weights-only loader is unsafe (< 2.10.0).

torch.load(weights_only=True) runs a crafted file's code below 2.6 (CVE-2025-32434) and
can corrupt memory up to 2.9.1 (GHSA-63cw-57p8-fm3p). pyproject.toml asks for 2.10, but
a user can pin any torch: model files, checkpoints and pretrained weights are refused
in one line, before anything is read.
"""

import numpy as np
import pytest
import torch

from relocfw import Pose, Relocalizer, load_model, save_model
from relocfw.core.errors import DataError
from relocfw.model import checkpoints
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet, load_imagenet_weights

OPTIONS = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 16}}
UNSAFE = ["2.1.0", "2.5.1+cu121", "2.6.0", "2.9.1+cpu", "2.10.0rc1", "2.10.0a0+git1234"]
SAFE = ["2.10.0", "2.10.0+cpu", "2.10.1", "2.13.0+cpu", "3.0.0"]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    torch.manual_seed(0)
    relocalizer = Relocalizer(
        PoseNet(**OPTIONS["backbone"]).eval(), ExhaustiveIndex(), CentreCrop()
    )
    images = [np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)]
    relocalizer.fit(images, [Pose([0.0, 0, 0], [1, 0, 0, 0]), Pose([1.0, 0, 0], [0, 1, 0, 0])])
    return save_model(tmp_path_factory.mktemp("floor") / "model.relocfw", relocalizer, OPTIONS, {})


@pytest.fixture
def torch_load_calls(monkeypatch):
    """Every call to torch.load from here on (the file must not even be opened)."""
    calls = []
    real = torch.load

    def recorded(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "load", recorded)
    return calls


def assert_one_line_refusal(error: DataError, path, version: str) -> None:
    message = str(error)
    assert "\n" not in message
    assert str(path) in message and f"torch {version}" in message
    assert "torch>=2.10.0" in message and "CVE-2025-32434" in message


@pytest.mark.parametrize("version", UNSAFE)
def test_load_model_refuses_under_an_unsafe_torch_without_reading_the_file(
    model_path, torch_load_calls, monkeypatch, version
):
    monkeypatch.setattr(torch, "__version__", version)
    with pytest.raises(DataError) as caught:
        load_model(model_path)
    assert_one_line_refusal(caught.value, model_path, version)
    assert torch_load_calls == []


@pytest.mark.parametrize("version", SAFE)
def test_load_model_reads_the_file_under_a_safe_torch(model_path, monkeypatch, version):
    monkeypatch.setattr(torch, "__version__", version)
    assert isinstance(load_model(model_path), Relocalizer)


def test_checkpoints_and_pretrained_weights_are_refused_too(
    model_path, torch_load_calls, monkeypatch
):
    # Both read through read_torch_file, as model files do.
    monkeypatch.setattr(torch, "__version__", "2.9.1")
    with pytest.raises(DataError) as caught:
        checkpoints.load_checkpoint(model_path)
    assert_one_line_refusal(caught.value, model_path, "2.9.1")
    with pytest.raises(DataError) as caught:
        load_imagenet_weights(PoseNet(input_size=32, width=0.125, feature_dim=16), model_path)
    assert_one_line_refusal(caught.value, model_path, "2.9.1")
    assert caught.value.args[0].startswith("backbone.weights: refused to read")
    assert torch_load_calls == []


def test_an_unreadable_torch_version_is_not_trusted(model_path, monkeypatch):
    monkeypatch.setattr(torch, "__version__", "unknown")
    with pytest.raises(DataError, match="with torch unknown"):
        load_model(model_path)
