"""A model file whose refiner holds a size far beyond any use, or a camera no real
camera has, is refused on loading in one line naming the file and the key, not left
to fail at every query (an uncaught cv2.error for max_features 2**40)."""

from __future__ import annotations

import pytest
import torch

from relocfw import DataError
from relocfw.model.model_file import load_model
from tests.model.test_model_file_refiner_map import depth_model, scene  # noqa: F401 (fixtures)

pytest.importorskip("poselib")


def forged(path, tmp_path, change) -> object:
    payload = torch.load(path, weights_only=True)
    change(payload["refine"])
    target = tmp_path / "forged.relocfw"
    torch.save(payload, target)
    return target


@pytest.mark.parametrize(
    ("where", "key", "value"),
    [
        ("state", "max_features", torch.tensor(2**40)),
        ("options", "max_features", 2**40),
        ("state", "count", torch.tensor(2**40)),
        ("options", "min_inliers", 2**40),
    ],
)
def test_a_size_beyond_any_use_is_refused_naming_the_file_and_key(
    depth_model,  # noqa: F811
    tmp_path,
    where,
    key,
    value,
):
    def change(part):
        part[where][key] = value

    path = forged(depth_model[1], tmp_path, change)
    with pytest.raises(DataError, match=rf"refine\.{key} must be at most") as caught:
        load_model(path)
    assert str(caught.value).startswith(str(path)) and "\n" not in str(caught.value)


@pytest.mark.parametrize(("column", "value", "key"), [(2, 1e300, "cx"), (4, 1e15, "width")])
def test_an_implausible_map_camera_is_refused_naming_the_file_and_key(
    depth_model,  # noqa: F811
    tmp_path,
    column,
    value,
    key,
):
    def change(part):
        part["state"]["cameras"][0, column] = value

    path = forged(depth_model[1], tmp_path, change)
    with pytest.raises(DataError, match=rf"cameras\[0\]: .*\b{key}\b") as caught:
        load_model(path)
    assert str(caught.value).startswith(str(path))
