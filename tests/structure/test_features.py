"""SIFT keypoints with RootSIFT descriptors on a textured synthetic image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.structure.features import LocalFeatures, extract_rootsift, root_sift


def textured_image(seed: int = 0, width: int = 320, height: int = 240) -> np.ndarray:
    """Blurred colour noise with drawn shapes: corners and blobs for SIFT to find."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.integers(0, 256, (height, width, 3), dtype=np.uint8), (7, 7), 2)
    for _ in range(30):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, [width, height]))
        if rng.random() < 0.5:
            cv2.rectangle(image, (x, y), (x + int(rng.integers(5, 40)), y + 20), colour, -1)
        else:
            cv2.circle(image, (x, y), int(rng.integers(3, 20)), colour, -1)
    return image


def test_rootsift_descriptors_have_unit_norm_and_the_keypoints_lie_in_the_image():
    image = textured_image()
    features = extract_rootsift(image, max_features=500)
    assert 50 < len(features) <= 500
    assert features.keypoints.dtype == np.float32 and features.keypoints.shape[1] == 2
    assert features.descriptors.dtype == np.float32 and features.descriptors.shape[1] == 128
    assert np.allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-5)
    assert (features.descriptors >= 0).all()
    assert (features.keypoints >= -0.5).all()
    assert (features.keypoints[:, 0] < image.shape[1]).all()
    assert (features.keypoints[:, 1] < image.shape[0]).all()


@pytest.mark.parametrize("max_features", [1, 7, 64])
def test_at_most_max_features(max_features):
    features = extract_rootsift(textured_image(1), max_features=max_features)
    assert 0 < len(features) <= max_features


def test_rootsift_distance_is_the_hellinger_kernel_of_sift():
    rng = np.random.default_rng(2)
    sift = rng.random((2, 128)).astype(np.float32) * 100
    a, b = root_sift(sift)
    p, q = sift / sift.sum(axis=1, keepdims=True)
    assert np.isclose(np.sum((a - b) ** 2), 2 - 2 * np.sum(np.sqrt(p * q)), atol=1e-5)


def test_a_blank_image_has_no_features():
    features = extract_rootsift(np.full((120, 160, 3), 128, dtype=np.uint8))
    assert features.keypoints.shape == (0, 2) and features.descriptors.shape == (0, 128)


def test_the_same_image_gives_the_same_features():
    first = extract_rootsift(textured_image(3), max_features=100)
    second = extract_rootsift(textured_image(3), max_features=100)
    assert np.array_equal(first.keypoints, second.keypoints)
    assert np.array_equal(first.descriptors, second.descriptors)


@pytest.mark.parametrize(
    "image, message",
    [
        (np.zeros((40, 40, 3), dtype=np.float32), "dtype float32"),
        (np.zeros((40, 40), dtype=np.uint8), "shape \\(40, 40\\)"),
        (np.zeros((40, 40, 4), dtype=np.uint8), "shape \\(40, 40, 4\\)"),
        ([[0, 0, 0]], "relocfw takes numpy arrays"),
    ],
)
def test_a_wrong_image_type_raises_one_data_error(image, message):
    with pytest.raises(DataError, match=message):
        extract_rootsift(image)


@pytest.mark.parametrize("max_features", [0, -1, 2.5, "many"])
def test_an_impossible_max_features_raises_a_config_error(max_features):
    with pytest.raises(ConfigError, match="max_features"):
        extract_rootsift(textured_image(), max_features=max_features)


def test_a_max_features_beyond_any_use_is_a_config_error_not_an_opencv_one():
    # OpenCV's SIFT raises its own error for 2**40 (a forged option would reach it).
    message = r"^max_features must be at most 100000, got 1099511627776"
    with pytest.raises(ConfigError, match=message):
        extract_rootsift(textured_image(), max_features=2**40)


def test_local_features_check_their_shapes_and_are_read_only():
    features = LocalFeatures(np.zeros((3, 2)), np.ones((3, 128)))
    assert features.keypoints.dtype == np.float32 and len(features) == 3
    with pytest.raises(ValueError):
        features.descriptors[0, 0] = 5.0
    with pytest.raises(DataError, match="3 keypoints but 2 descriptors"):
        LocalFeatures(np.zeros((3, 2)), np.ones((2, 128)))
    with pytest.raises(DataError, match="keypoints must be an \\[N, 2\\]"):
        LocalFeatures(np.zeros((3, 3)), np.ones((3, 128)))
    with pytest.raises(DataError, match="finite"):
        LocalFeatures(np.full((1, 2), np.nan), np.ones((1, 128)))
