"""Very thin images: refused by shape (query.max_aspect) before their strip is built,
on the header where there is one and on the pixels always; every crop search capped
in the windows it may ask for (query.max_candidates); an allocation that fails is one
DataError naming the limits."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from relocfw import QueryOptions, Relocalizer
from relocfw.core import imaging
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import Strip, read_rgb
from relocfw.core.interfaces import SearchQuery
from relocfw.core.values import Pose
from relocfw.data.frames import Frame, read_images
from relocfw.data.intrinsics import image_size
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop
from relocfw.plugins.window_rule_crop import WindowRuleSearch


def thin_png(path, width: int, height: int = 1):
    cv2.imwrite(str(path), np.full((height, width, 3), 90, np.uint8))
    return path


@pytest.mark.parametrize("width", [5000, 300000])
def test_read_rgb_refuses_a_thin_png_on_its_header(tmp_path, width):
    path = thin_png(tmp_path / "thin.png", width)
    assert path.stat().st_size < 1500
    with pytest.raises(DataError) as refused:
        read_rgb(path, max_aspect=10, key="query.max_aspect")
    message = str(refused.value)
    assert message.startswith(f"{path}: its header announces {width} x 1 pixels")
    assert "query.max_aspect=10 allows" in message and "\n" not in message


def test_read_rgb_checks_the_pixels_of_formats_whose_header_is_not_read(tmp_path):
    path = tmp_path / "thin.bmp"
    cv2.imwrite(str(path), np.zeros((2, 50, 3), np.uint8))
    with pytest.raises(DataError, match=r"thin\.bmp is 50 x 2 pixels, its long side 25 times"):
        read_rgb(path, max_aspect=10)
    assert read_rgb(path, max_aspect=25).shape == (2, 50, 3)


def test_map_images_are_read_with_no_aspect_limit_and_no_key_is_named(tmp_path):
    # Map images are not queries: a 1200 x 100 one reads (the pixel limit still holds),
    # and the camera's size is taken from it, not from the next image.
    thin = tmp_path / "thin.png"
    cv2.imwrite(str(thin), np.full((100, 1200, 3), 90, np.uint8))
    square = tmp_path / "square.png"
    cv2.imwrite(str(square), np.full((100, 100, 3), 90, np.uint8))
    assert read_rgb(thin).shape == (100, 1200, 3)
    frame = Frame("thin", thin, Pose([0.0, 0.0, 0.0], [1.0, 0, 0, 0]))
    assert read_images([frame], quiet=True)[0].shape == (100, 1200, 3)
    assert image_size([thin, square]) == (1200, 100)
    # A limit that no option sets names no option.
    with pytest.raises(DataError) as refused:
        read_rgb(thin, max_aspect=5)
    message = str(refused.value)
    assert message.startswith(f"{thin}: its header announces 1200 x 100 pixels")
    assert "more than 5 allows (crop the image)" in message and "query." not in message


def relocalizer(search=None, **options) -> Relocalizer:
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=16)
    found = Relocalizer(backbone, ExhaustiveIndex(), search or SweepCrop(), QueryOptions(**options))
    images = [np.full((24, 32, 3), value, np.uint8) for value in (0, 120, 240)]
    found.fit(images, [Pose([float(i), 0.0, 0.0], [1.0, 0, 0, 0]) for i in range(3)])
    return found


def test_a_query_thinner_than_max_aspect_is_refused_before_its_strip():
    strips = []
    reloc = relocalizer()
    original = reloc.scorer.strip
    reloc.scorer.strip = lambda image: strips.append(image.shape) or original(image)
    with pytest.raises(DataError, match=r"^the query image is 5000 x 1 pixels.*max_aspect=10"):
        reloc.localize(np.zeros((1, 5000, 3), np.uint8))
    with pytest.raises(DataError, match=r"^image 1 is 1 x 40 pixels, its long side 40 times"):
        reloc.localize_many([np.zeros((24, 32, 3), np.uint8), np.zeros((40, 1, 3), np.uint8)])
    assert strips == []
    # Raised, the limit lets the same image through (a 1 x 50 strip: 49 windows).
    wide = relocalizer(max_aspect=60).localize(np.zeros((1, 50, 3), np.uint8))
    assert wide.crop.size == 1


@pytest.mark.parametrize(
    "search",
    [SweepCrop(), WindowRuleSearch("mean"), GeneticCropSearch(population=40, iterations=0)],
    ids=["sweep", "rule", "ga"],
)
def test_every_crop_search_is_capped_before_any_window_is_scored(search):
    reloc = relocalizer(search, max_candidates=20)
    scored = []
    original = reloc.scorer.plain_together
    reloc.scorer.plain_together = lambda requests: scored.append(requests) or original(requests)
    # 24 x 200: the strip is 32 x 267, so 236 distinct windows along it.
    with pytest.raises(DataError) as refused:
        reloc.localize(np.zeros((24, 200, 3), np.uint8))
    message = str(refused.value)
    assert "candidate windows of the 200 x 24 query image" in message
    assert "more than query.max_candidates=20 allows" in message
    assert scored == []


def test_the_default_cap_leaves_a_sweep_of_the_thinnest_image_allowed():
    options = QueryOptions()
    assert (options.max_aspect, options.max_candidates) == (10.0, 4096)
    # A 224 network trained at crop_scale 256/224 cuts 256-pixel windows from the
    # strip: a sweep of a 10:1 image asks for (10 - 1) x 256 + 1 distinct ones.
    strip = Strip(np.zeros((400, 4000, 3), np.uint8), 224, 256 / 224)
    crops = next(SweepCrop().propose(SearchQuery(4000, 400)))
    windows = {strip.window(crop) for crop in crops}
    assert (len(crops), len(windows)) == (3601, 2305)
    assert len(windows) <= options.max_candidates


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("max_aspect", 0.5, "max_aspect must be at least 1"),
        ("max_aspect", float("inf"), "max_aspect must be finite"),
        ("max_aspect", True, "max_aspect must be a number"),
        ("max_candidates", 0, "max_candidates must be at least 1"),
    ],
)
def test_the_limits_are_checked_options(key, value, message):
    with pytest.raises(ConfigError, match=message):
        QueryOptions(**{key: value})


def test_options_stored_before_the_limits_existed_load_with_the_defaults():
    stored = {"batch_size": 16, "scoring": "plain", "rerank": 1, "crop_samples": 0}
    options = QueryOptions.from_mapping(stored, where="model.relocfw: query options")
    assert (options.max_aspect, options.max_candidates) == (10.0, 4096)
    assert QueryOptions(max_aspect=20).as_dict()["max_aspect"] == 20.0


def test_a_strip_that_cannot_be_allocated_is_a_data_error_naming_the_limits(monkeypatch):
    def failing(*_, **__):
        raise cv2.error("OpenCV(4) error: (-4:Insufficient memory) Failed to allocate 45 bytes")

    monkeypatch.setattr(imaging.cv2, "resize", failing)
    with pytest.raises(DataError) as refused:
        Strip(np.zeros((1, 9, 3), np.uint8), 224)
    message = str(refused.value)
    assert message.startswith("a 9 x 1 image: out of memory scaling it to its 2016 x 224 strip")
    assert "Failed to allocate 45 bytes" in message and "query.max_aspect" in message

    def out_of_memory(*_, **__):
        raise MemoryError

    monkeypatch.setattr(imaging.cv2, "resize", out_of_memory)
    with pytest.raises(DataError, match=r"out of memory .*query\.max_aspect"):
        Strip(np.zeros((1, 9, 3), np.uint8), 224)


def test_a_model_file_stored_before_the_limits_existed_loads_with_the_defaults(tmp_path):
    from relocfw.model.model_file import load_model, save_model

    parts = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 16}}
    path = save_model(tmp_path / "model.relocfw", relocalizer(), parts, {})
    payload = torch.load(path, weights_only=True)
    for key in ("max_aspect", "max_candidates"):
        del payload["query"][key]
    torch.save(payload, path)
    loaded = load_model(path)
    assert (loaded.options.max_aspect, loaded.options.max_candidates) == (10.0, 4096)
    raised = load_model(path, overrides={"max_aspect": 50.0, "max_candidates": None})
    assert (raised.options.max_aspect, raised.options.max_candidates) == (50.0, 4096)
