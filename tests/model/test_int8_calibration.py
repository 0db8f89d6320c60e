"""Static int8 (onnx.int8=static) is calibrated well: its descriptors stay within a
measured distance of float32's on the map images and on queries it never saw.

Finite answers prove little: calibrating on 0-255 pixels instead of the network's
0-1 inputs, or on one map image instead of spreading over the map, still answers
finite numbers, only worse ones. The map here varies in exposure (a dim, flat first
frame, then others of various colour casts and contrasts), as a recording does, so
ranges taken from a single image clip the others.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from relocfw.core.imaging import Strip
from relocfw.core.pipeline import Relocalizer
from relocfw.model.onnx_backbone import OnnxBackbone
from relocfw.model.onnx_engine import EngineOptions, onnx_engine
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet

pytest.importorskip("onnx", reason='onnx not installed (pip install "relocfw[onnx]")')
pytest.importorskip("onnxruntime", reason='onnxruntime not installed ("relocfw[onnx]")')

# The largest relative deviation |int8 - float32| / |float32| of a descriptor allowed.
# MEASURED on this network and these images (x86, 7-bit weights): 0.016-0.036 on the
# six map images, 0.027 and 0.058 on the two queries. The slips this guards against
# give, on the same images: calibration on the first image only 0.26-0.51 on the
# other map images and 0.43-0.45 on the queries; calibration on 0-255 pixels 1.0-7.2
# (every descriptor lost). 0.12 is about twice the worst genuine deviation.
MAX_RELATIVE_DEVIATION = 0.12
# Below this a graph is not quantised at all (float32 agrees with torch to ~1e-6).
MIN_RELATIVE_DEVIATION = 1e-3


def tiny_network() -> PoseNet:
    """A tiny PoseNet whose maps keep their size through the blocks (0.8 of He's
    initialisation; torch's default shrinks them to ~1e-5, where int8 and float32
    cannot be told apart)."""
    torch.manual_seed(0)
    network = PoseNet(input_size=64, width=0.25, feature_dim=32).eval()
    with torch.no_grad():
        for module in network.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, nonlinearity="relu").mul_(0.8)
    return network


def varied_exposure_images(count: int = 8, seed: int = 0) -> list[np.ndarray]:
    """60 x 80 RGB frames of smooth structure plus fine noise, each with its own
    colour cast and contrast; the first is dim and flat."""
    rng = np.random.default_rng(seed)
    frames = []
    for number in range(count):
        coarse = rng.normal(0, 1, (8, 10, 3)).astype(np.float32)
        smooth = cv2.resize(coarse, (80, 60), interpolation=cv2.INTER_CUBIC)
        fine = rng.normal(0, 1, (60, 80, 3)).astype(np.float32)
        contrast, cast = rng.uniform(25, 70), rng.uniform(60, 195, 3)
        if number == 0:
            contrast, cast = 8.0, np.full(3, 50.0)
        frame = cast + contrast * (smooth + 0.5 * fine)
        frames.append(np.clip(frame, 0, 255).astype(np.uint8))
    return frames


def centre_windows(images: list[np.ndarray], network: PoseNet) -> torch.Tensor:
    """uint8 [n, 3, s, s]: the centre crops the map is described by."""
    windows = []
    for image in images:
        strip = Strip(image, network.input_size, float(network.crop_scale))
        windows.append(strip.cut(strip.window(strip.centre_crop())))
    return torch.stack(windows)


@pytest.fixture(scope="module")
def network() -> PoseNet:
    return tiny_network()


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    return varied_exposure_images()


@pytest.fixture(scope="module")
def scout(network, images, tmp_path_factory) -> OnnxBackbone:
    """The network's engine with the static int8 full graph (calibrated on the first
    six images, the map) as its scout: only that graph is quantised."""
    owner: Path = tmp_path_factory.mktemp("int8-calibration") / "net.pt"
    options = EngineOptions(threads=1, int8="static", scout=True)
    return onnx_engine(network, owner, options, images[:6], say=lambda note: None)


def relative_deviations(network, scout, images) -> np.ndarray:
    """[n] |int8 - float32| / |float32| of each image's centre-crop descriptor."""
    exact = Relocalizer(network, ExhaustiveIndex(), CentreCrop()).describe(images)
    with torch.inference_mode():
        rounded = scout.scout_features(centre_windows(images, network).float() / 255).numpy()
    return np.linalg.norm(rounded - exact, axis=1) / np.linalg.norm(exact, axis=1)


def test_int8_descriptors_of_the_map_stay_near_float32(network, scout, images):
    deviations = relative_deviations(network, scout, images[:6])
    assert deviations.min() > MIN_RELATIVE_DEVIATION  # a genuine int8 graph
    assert deviations.max() < MAX_RELATIVE_DEVIATION, deviations.round(3)


def test_int8_descriptors_of_unseen_queries_stay_near_float32(network, scout, images):
    deviations = relative_deviations(network, scout, images[6:])
    assert deviations.min() > MIN_RELATIVE_DEVIATION
    assert deviations.max() < MAX_RELATIVE_DEVIATION, deviations.round(3)
