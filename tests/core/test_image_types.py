"""Images of the wrong type are refused at every public entry, by dtype or shape."""

import numpy as np
import pytest
import torch

from relocfw import Relocalizer
from relocfw.core.errors import DataError
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.report.window_scores import score_windows


def rgb(seed: int, height: int = 36, width: int = 48) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def relocalizer():
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=16)
    fitted = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop())
    fitted.fit([rgb(seed) for seed in range(4)])
    return fitted


# What a user might hand over instead of H x W x 3 uint8, and what the message names.
WRONG = {
    "float in [0, 1]": (rgb(9).astype(np.float32) / 255, "dtype float32"),
    "uint16": (rgb(9).astype(np.uint16) * 257, "dtype uint16"),
    "greyscale": (rgb(9)[:, :, 0], r"shape \(36, 48\)"),
    "RGBA": (np.dstack([rgb(9), np.full((36, 48), 255, np.uint8)]), r"shape \(36, 48, 4\)"),
    "a torch tensor": (torch.zeros(36, 48, 3, dtype=torch.uint8), "is a Tensor"),
}


def entries(relocalizer, image):
    """Every public entry that takes images, each called with `image`."""
    return {
        "localize": lambda: relocalizer.localize(image),
        "score_windows": lambda: score_windows(relocalizer, image),
        "describe": lambda: relocalizer.describe([image]),
        "fit": lambda: relocalizer.fit([image]),
        "localize_many": lambda: relocalizer.localize_many([image]),
    }


@pytest.mark.parametrize("case", WRONG)
@pytest.mark.parametrize("entry", ["localize", "score_windows", "describe", "fit", "localize_many"])
def test_an_image_of_the_wrong_type_is_refused_naming_its_dtype_or_shape(relocalizer, case, entry):
    image, named = WRONG[case]
    with pytest.raises(DataError, match=named):
        entries(relocalizer, image)[entry]()


def test_a_list_with_one_bad_image_names_its_index_before_any_query_runs(relocalizer):
    calls = []
    hook = relocalizer.backbone.register_forward_hook(lambda *_: calls.append(1))
    images = [rgb(1), rgb(2), rgb(3).astype(np.float64) / 255, rgb(4)]
    try:
        with pytest.raises(DataError, match=r"^image 2 has dtype float64"):
            relocalizer.localize_many(images, queries_at_once=2)
        with pytest.raises(DataError, match=r"^image 2 has dtype float64"):
            relocalizer.describe(images)
    finally:
        hook.remove()
    assert calls == []  # refused up front, not after the first group


def test_valid_uint8_images_still_localize_and_are_checked_without_a_copy(relocalizer):
    from relocfw.core.imaging import check_rgb_image  # here: the old code lacks it

    image = rgb(5)
    assert check_rgb_image(image) is image
    answer = relocalizer.localize(image)
    assert np.isfinite(answer.pose.position).all()
    many = relocalizer.localize_many([image, rgb(6)], queries_at_once=2)
    assert np.allclose(many[0].pose.position, answer.pose.position, atol=1e-5)
    assert relocalizer.describe([image, rgb(6)]).shape == (2, 16)


def test_a_16_bit_depth_png_is_not_read_as_a_colour_image(tmp_path):
    import cv2

    from relocfw.core.imaging import read_rgb

    depth = tmp_path / "frame-000000.depth.png"
    cv2.imwrite(str(depth), np.full((4, 6), 1500, dtype=np.uint16))
    with pytest.raises(DataError, match="16-bit single-channel PNG \\(a depth map\\?\\)"):
        read_rgb(depth)
    colour = tmp_path / "grey.png"
    cv2.imwrite(str(colour), np.full((4, 6), 200, dtype=np.uint8))
    assert read_rgb(colour).shape == (4, 6, 3)  # an 8-bit grey image is still read
