"""A damaged model file ends in one DataError naming the file and the part, never in a
traceback, a NaN answer or a huge allocation.

Each damaged file is a real saved model, loaded with torch, edited the named way and
saved again: what a truncated copy, a bad edit or a crafted file would leave.
"""

import time
from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import Pose, Relocalizer, load_model, save_model
from relocfw.core.errors import DataError
from relocfw.model import pose_head, stored_parts
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet

OPTIONS = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 16}}
IMAGES = [np.full((36, 48, 3), value, np.uint8) for value in (0, 90, 200)]
POSES = [Pose([float(i), 0, 0], [1, 0, 0, 0]) for i in range(len(IMAGES))]


def saved(tmp_path_factory, index, options=OPTIONS) -> dict:
    """The payload of a genuine model file with `index`, after checking that it loads."""
    torch.manual_seed(0)
    relocalizer = Relocalizer(PoseNet(**options["backbone"]).eval(), index, CentreCrop())
    relocalizer.fit(IMAGES, POSES)
    path = save_model(
        tmp_path_factory.mktemp("genuine") / "model.relocfw", relocalizer, options, {}
    )
    assert np.isfinite(load_model(path).localize(IMAGES[1]).distance)  # it loads and answers
    return torch.load(path, weights_only=True)


@pytest.fixture(scope="module")
def exhaustive_payload(tmp_path_factory):
    return saved(tmp_path_factory, ExhaustiveIndex())


@pytest.fixture(scope="module")
def kmeans_payload(tmp_path_factory):
    return saved(tmp_path_factory, KMeansIndex(k=2), {**OPTIONS, "index": {"k": 2}})


def written(payload: dict, tmp_path: Path) -> Path:
    path = tmp_path / "damaged.relocfw"
    torch.save(payload, path)
    return path


def edited(payload: dict, part: str, **state) -> dict:
    """A copy of `payload` with entries of `part`'s state replaced."""
    return {**payload, part: {**payload[part], "state": {**payload[part]["state"], **state}}}


def refused(path: Path, *named: str) -> str:
    """load_model's one-line DataError for `path`; it names the file and each of `named`."""
    with pytest.raises(DataError) as caught:
        load_model(path)
    message = str(caught.value)
    assert "\n" not in message, message
    assert message.startswith(f"{path}: damaged model file ("), message
    for name in named:
        assert name in message, message
    return message


@pytest.mark.parametrize(
    ("map_poses", "said"),
    [
        ([[0.0, 0, 0, 1, 0, 0, 0]] * 3, "got a list"),
        (torch.zeros(3, 2, dtype=torch.float64), "got shape [3, 2]"),
        (torch.full((3, 7), float("nan"), dtype=torch.float64), "NaN or infinite"),
    ],
    ids=["list", "shape N x 2", "NaN"],
)
def test_damaged_map_poses_are_one_data_error(exhaustive_payload, tmp_path, map_poses, said):
    path = written({**exhaustive_payload, "map_poses": map_poses}, tmp_path)
    refused(path, "map_poses", said)


def test_a_file_without_metadata_is_one_data_error(exhaustive_payload, tmp_path):
    payload = dict(exhaustive_payload)
    del payload["metadata"]
    refused(written(payload, tmp_path), "metadata must be a mapping, got NoneType")


def nan_at_first(tensor: torch.Tensor) -> torch.Tensor:
    damaged = tensor.clone()
    damaged.view(-1)[0] = float("nan")
    return damaged


@pytest.mark.parametrize("key", ["points", "mean", "std"])
def test_nan_in_the_exhaustive_map_is_refused_at_load(exhaustive_payload, tmp_path, key):
    state = exhaustive_payload["index"]["state"]
    path = written(edited(exhaustive_payload, "index", **{key: nan_at_first(state[key])}), tmp_path)
    refused(path, "index:", "NaN or infinite")


def test_nan_kmeans_centres_are_refused_at_load(kmeans_payload, tmp_path):
    centres = nan_at_first(kmeans_payload["index"]["state"]["centres"])
    refused(
        written(edited(kmeans_payload, "index", centres=centres), tmp_path), "index:", "centres"
    )


@pytest.mark.parametrize("payload_name", ["exhaustive_payload", "kmeans_payload"])
def test_a_zero_std_in_the_standardiser_is_refused_at_load(request, tmp_path, payload_name):
    payload = request.getfixturevalue(payload_name)
    std = payload["index"]["state"]["std"].clone()
    std[3] = 0.0
    refused(written(edited(payload, "index", std=std), tmp_path), "index:", "std must be above 0")


def test_an_index_map_of_other_descriptors_than_the_network_makes_is_refused(
    exhaustive_payload, tmp_path
):
    state = {
        key: value[..., :8].clone() for key, value in exhaustive_payload["index"]["state"].items()
    }
    path = written(edited(exhaustive_payload, "index", **state), tmp_path)
    refused(path, "index:", "8-dimensional descriptors, the backbone makes 16")


def test_nan_backbone_weights_are_refused_at_load(exhaustive_payload, tmp_path):
    key = "head.descriptor.weight"
    path = written(
        edited(
            exhaustive_payload,
            "backbone",
            **{key: nan_at_first(exhaustive_payload["backbone"]["state"][key])},
        ),
        tmp_path,
    )
    refused(path, "backbone:", key, "NaN or infinite")


@pytest.fixture
def no_real_huge_heads(monkeypatch):
    """Stops (MemoryError) any PoseHead built with real storage for more than 1000
    descriptor dimensions, before it allocates: what a crafted feature_dim would cost.
    Built on the meta device (no storage), it is left alone."""
    real_init = pose_head.PoseHead.__init__

    def guarded(self, in_features, feature_dim, dropout):
        if feature_dim > 1000 and torch.empty(0).device.type != "meta":
            raise MemoryError(f"a real PoseHead of {feature_dim} dimensions")
        real_init(self, in_features, feature_dim, dropout)

    monkeypatch.setattr(pose_head.PoseHead, "__init__", guarded)


def with_backbone_options(payload: dict, **options) -> dict:
    backbone = payload["backbone"]
    return {**payload, "backbone": {**backbone, "options": {**backbone["options"], **options}}}


@pytest.mark.parametrize(
    ("feature_dim", "said"),
    [
        (10**9, "option feature_dim=1000000000 is above 65536"),
        # Under the cap, but not the weights' size: found on the meta device.
        (60000, "options do not fit its weights (head.descriptor.weight is [16, 128]"),
    ],
    ids=["above the cap", "not the weights' size"],
)
def test_a_crafted_feature_dim_is_refused_quickly_without_allocating(
    exhaustive_payload, tmp_path, no_real_huge_heads, feature_dim, said
):
    path = written(with_backbone_options(exhaustive_payload, feature_dim=feature_dim), tmp_path)
    started = time.perf_counter()
    refused(path, "backbone:", said)
    assert time.perf_counter() - started < 5


@pytest.mark.parametrize(
    ("option", "said"),
    [
        ({"width": 0.25}, "options do not fit its weights"),
        ({"width": 100}, "width must be in"),
        ({"input_size": 10**7}, "option input_size=10000000 is above 65536"),
        ({"decoder_channels": [8, 10**8]}, "option decoder_channels=[8, 100000000] is above"),
    ],
    ids=["width that fits no weight", "width out of range", "input size", "in a list"],
)
def test_backbone_options_that_do_not_fit_are_one_data_error(
    exhaustive_payload, tmp_path, option, said
):
    refused(
        written(with_backbone_options(exhaustive_payload, **option), tmp_path), "backbone:", said
    )


def test_a_faiss_index_of_another_dimension_is_refused_at_load(tmp_path_factory, tmp_path):
    pytest.importorskip("faiss")
    from relocfw.plugins.faiss_index import FaissIndex

    payload = saved(tmp_path_factory, FaissIndex())
    other = FaissIndex()
    other.fit(np.random.default_rng(0).normal(size=(20, 8)))
    blob = other.state()["faiss_index"]
    path = written(edited(payload, "index", faiss_index=blob), tmp_path)
    refused(path, "index:", "faiss_index holds 8-dimensional descriptors, the standardisation 16")


@pytest.fixture(scope="module")
def sequence_state():
    """The state of a small fitted refine=sequence (hidden=8): two recordings of 6 frames."""
    from relocfw import MapImage
    from relocfw.plugins.sequence_refiner import SequenceRefiner

    rng = np.random.default_rng(0)
    views = [
        MapImage(
            f"seq-{r}/frame-{i}",
            np.zeros((4, 4, 3), np.uint8),
            Pose(rng.normal(size=3), [1, 0, 0, 0]),
        )
        for r in range(2)
        for i in range(6)
    ]
    refiner = SequenceRefiner(window=3, hidden=8, steps=2)
    refiner.fit(views, rng.normal(size=(len(views), 16)))
    return refiner.state()


@pytest.mark.parametrize("hidden", [60000, 10**9], ids=["large", "past any tensor"])
def test_a_crafted_sequence_hidden_is_refused_without_building_the_network(
    sequence_state, monkeypatch, hidden
):
    from relocfw.plugins import sequence_refiner

    real = sequence_refiner.SequencePoseNetwork

    def guarded(feature_dim, size, *rest):
        if size > 1000 and torch.empty(0).device.type != "meta":
            raise MemoryError(f"a real sequence network of hidden={size}")
        return real(feature_dim, size, *rest)

    monkeypatch.setattr(sequence_refiner, "SequencePoseNetwork", guarded)
    started = time.perf_counter()
    with pytest.raises(DataError, match=rf"do not fit refine.hidden={hidden}"):
        sequence_refiner.SequenceRefiner(window=3, hidden=hidden).load_state(sequence_state)
    assert time.perf_counter() - started < 5


def test_only_size_options_are_capped():
    # A plugin's seed or step count may rightly be large; sizes are what allocate.
    assert stored_parts.oversized_option({"seed": 123456789, "steps": 10**6}) is None
    assert stored_parts.oversized_option({"hidden_dim": 10**6}) == "hidden_dim=1000000"
