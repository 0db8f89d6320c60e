"""Model files: a saved and reloaded Relocalizer answers exactly as the original."""

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, PoseRefiner, QueryOptions, Refined, Relocalizer
from relocfw.data.frames import read_images
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.model.model_file import MODEL_FORMAT, load_model, save_model, stores_refiner
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.retrieval_refiner import RetrievalRefiner
from relocfw.plugins.sweep_crop import SweepCrop


@pytest.fixture(scope="module")
def scene(tiny_scene):
    train = load_sevenscenes(tiny_scene, None, "train")
    test = load_sevenscenes(tiny_scene, None, "test")
    return train, read_images(train, quiet=True), read_images(test, quiet=True)


def tiny_backbone(**options):
    """A seeded tiny PoseNet and the options it was built with."""
    options = {"input_size": 32, "width": 0.0625, "feature_dim": 16, **options}
    torch.manual_seed(0)
    backbone = PoseNet(**options)
    # Training would set these; values away from the defaults show they are saved.
    backbone.set_position_normalisation(np.array([1.0, -2.0, 0.5]), 3.0)
    return backbone, options


def round_trip(relocalizer, options, tmp_path):
    path = save_model(tmp_path / "model.relocfw", relocalizer, options, {"scene": "tiny"})
    loaded = load_model(path)
    assert loaded.metadata == {"scene": "tiny"}
    return loaded


def answers(relocalizer, images):
    return [relocalizer.localize(image) for image in images]


def assert_same_answers(got, expected):
    for a, b in zip(got, expected, strict=True):
        assert a.crop == b.crop
        assert a.distance == pytest.approx(b.distance, rel=1e-9, abs=1e-12)
        assert np.allclose(a.pose.position, b.pose.position, rtol=1e-9, atol=1e-12)
        assert np.allclose(a.pose.quaternion, b.pose.quaternion, rtol=1e-9, atol=1e-12)
        assert np.array_equal(
            [a.position_spread, a.orientation_spread_deg],
            [b.position_spread, b.orientation_spread_deg],
            equal_nan=True,
        )


def test_retrieval_model_round_trip_answers_with_the_same_map_poses(scene, tmp_path):
    frames, train, test = scene
    backbone, options = tiny_backbone()
    # refine=retrieval beside k-means: retrieval needs no exhaustive index.
    refiner = RetrievalRefiner(k=2)
    relocalizer = Relocalizer(backbone, KMeansIndex(k=3), SweepCrop(), refiner=refiner)
    relocalizer.fit(train, [f.pose for f in frames])
    assert stores_refiner(relocalizer)
    parts = {"backbone": options, "index": {"k": 3}, "refine": {"k": 2}}
    loaded = round_trip(relocalizer, parts, tmp_path)
    assert isinstance(loaded.refiner, RetrievalRefiner) and loaded.refiner.k == 2
    assert loaded.refiner is not refiner
    payload = torch.load(tmp_path / "model.relocfw", weights_only=True)
    assert payload["refine"]["class"] == "relocfw.plugins.retrieval_refiner.RetrievalRefiner"
    assert payload["refine"]["options"] == {"k": 2}
    assert len(loaded.map_poses) == len(frames)
    for saved, original in zip(loaded.map_poses, frames, strict=True):
        assert np.allclose(saved.position, original.pose.position, rtol=0, atol=1e-12)
        assert np.allclose(saved.quaternion, original.pose.quaternion, rtol=0, atol=1e-12)
    expected = answers(relocalizer, test)
    assert_same_answers(answers(loaded, test), expected)
    for a, b in zip(answers(loaded, test), expected, strict=True):
        assert a.refine_confidence == b.refine_confidence < 0 and not a.fell_back
    # Retrieval really answered: the network's own pose of the same crop is elsewhere.
    network = Relocalizer(backbone, relocalizer.index, SweepCrop())
    own = answers(network, test)
    assert all(
        not np.allclose(a.pose.position, b.pose.position)
        for a, b in zip(expected, own, strict=True)
    )


class Unstorable(PoseRefiner):
    """A refiner without state(): model files leave it out, as they do refine=features."""

    def fit(self, views, descriptors, quiet=True):
        pass

    def refine(self, query):
        return Refined(query.network_pose)


def test_a_refiner_without_state_is_left_out_of_the_model_file(scene, tmp_path):
    frames, train, _ = scene
    backbone, options = tiny_backbone()
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), CentreCrop(), refiner=Unstorable())
    relocalizer.fit(train, [f.pose for f in frames])
    assert not stores_refiner(relocalizer)
    loaded = round_trip(relocalizer, {"backbone": options}, tmp_path)
    assert loaded.refiner is None
    assert "refine" not in torch.load(tmp_path / "model.relocfw", weights_only=True)


def test_mc_sampling_model_round_trip_gives_the_same_poses_and_spreads(scene, tmp_path):
    frames, train, test = scene
    backbone, options = tiny_backbone(mc_samples=8)
    relocalizer = Relocalizer(backbone, KMeansIndex(k=3), CentreCrop(), QueryOptions(sample_seed=7))
    relocalizer.fit(train)
    loaded = round_trip(relocalizer, {"backbone": options, "index": {"k": 3}}, tmp_path)
    assert loaded.backbone.mc_samples == 8 and loaded.options.sample_seed == 7
    expected = answers(relocalizer, test)
    assert all(np.isfinite(a.position_spread) and a.position_spread > 0 for a in expected)
    # The sample seed travels with the model file; torch's global stream plays no part.
    torch.manual_seed(123)
    assert_same_answers(answers(loaded, test), expected)
    # Sampling is live: another sample seed moves the answers.
    other = answers(loaded.replace(options=loaded.options.replace(sample_seed=8)), test)
    assert not np.allclose(other[0].pose.position, expected[0].pose.position)


def test_a_model_trained_on_posenet_crops_is_loaded_with_its_crop_scale(scene, tmp_path):
    _, train_images, test_images = scene
    backbone, options = tiny_backbone()
    backbone.set_crop_scale(256 / 224)  # as training with train.crop_scale=1.142857 does
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop())
    relocalizer.fit(train_images)
    expected = answers(relocalizer, test_images)
    loaded = round_trip(relocalizer, {"backbone": options}, tmp_path)
    assert loaded.crop_scale == pytest.approx(256 / 224)
    assert_same_answers(answers(loaded, test_images), expected)


# Every QueryOptions field away from its default, over two models (refine=retrieval
# cannot be combined with sampling): a model file must give each of them back.
STORED_OPTIONS = {
    "sampling": QueryOptions(
        batch_size=7, scoring="shared", rerank=3, crop_samples=3, sample_seed=5, queries_at_once=3
    ),
    "retrieval": QueryOptions(batch_size=5, queries_at_once=2, max_aspect=4, max_candidates=500),
}


def fitted_with(options: QueryOptions, scene, k: int = 0) -> tuple[Relocalizer, dict]:
    """A model with `options`, and refine=retrieval refine.k=k when k > 0."""
    frames, train, _ = scene
    backbone, backbone_options = tiny_backbone()
    backbone.set_crop_scale(1.5)  # crop sampling needs windows smaller than the crop
    refiner = RetrievalRefiner(k) if k > 0 else None
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), options, refiner=refiner)
    relocalizer.fit(train, [f.pose for f in frames])
    return relocalizer, {"backbone": backbone_options, "refine": {"k": k}}


@pytest.mark.parametrize("name", STORED_OPTIONS)
def test_format_3_stores_and_gives_back_every_query_option(scene, tmp_path, name):
    defaults = QueryOptions().as_dict()
    changed_somewhere = {
        key
        for other in STORED_OPTIONS.values()
        for key, value in other.as_dict().items()
        if value != defaults[key]
    }
    assert changed_somewhere == set(defaults)  # no field is tested at its default only
    options = STORED_OPTIONS[name]
    relocalizer, parts = fitted_with(options, scene, k=2 if name == "retrieval" else 0)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == MODEL_FORMAT == 5
    assert payload["query"] == options.as_dict()
    assert ("refine" in payload) == (name == "retrieval")
    loaded = load_model(path)
    assert loaded.options == options
    assert_same_answers(answers(loaded, scene[2]), answers(relocalizer, scene[2]))
    # An override changes its own field only; None keeps the file's value.
    changed = load_model(path, overrides={"queries_at_once": 4, "batch_size": None})
    assert changed.options == options.replace(queries_at_once=4)


def as_format_2(path, tmp_path, **stored) -> object:
    """The model file at `path` rewritten as format 2 wrote it: the query options it
    knew at the top level, no "query" mapping, no refiner."""
    payload = torch.load(path, weights_only=True)
    del payload["query"]
    payload.pop("refine", None)
    payload.update(format=2, **stored)
    old = tmp_path / "format2.relocfw"
    torch.save(payload, old)
    return old


def as_format_3(path, tmp_path, retrieval_k: int) -> object:
    """The model file at `path` rewritten as format 3 wrote it: retrieval as the query
    option retrieval_k, no refiner."""
    payload = torch.load(path, weights_only=True)
    payload.pop("refine", None)
    payload.update(format=3, query={**payload["query"], "retrieval_k": retrieval_k})
    old = tmp_path / "format3.relocfw"
    torch.save(payload, old)
    return old


@pytest.mark.parametrize(
    "stored",
    [
        {"retrieval_k": 2, "crop_samples": 0, "sample_seed": 0, "rerank": 1},
        {"retrieval_k": 0, "crop_samples": 3, "sample_seed": 4, "rerank": 2},
    ],
    ids=["retrieval", "sampling"],
)
def test_a_format_2_model_file_still_loads_with_its_query_options(scene, tmp_path, stored):
    rerank, k = stored["rerank"], stored["retrieval_k"]
    # The options format 2 stored, with plain scoring (which it did not store): a
    # re-ranking count only means something when shared scoring is asked for. Its
    # retrieval_k is refine=retrieval refine.k=retrieval_k.
    query = {key: value for key, value in stored.items() if key != "retrieval_k"}
    expected = QueryOptions(**{**query, "rerank": 1})
    relocalizer, parts = fitted_with(expected, scene, k)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    old = as_format_2(path, tmp_path, **stored)
    loaded = load_model(old)
    assert loaded.options == expected
    if k:
        assert isinstance(loaded.refiner, RetrievalRefiner) and loaded.refiner.k == k
    else:
        assert loaded.refiner is None
    assert loaded.metadata == {"scene": "tiny"}
    assert len(loaded.map_poses) == len(scene[0])
    assert_same_answers(answers(loaded, scene[2]), answers(relocalizer, scene[2]))
    # With shared scoring asked for, the stored re-ranking count comes back too.
    shared = load_model(old, overrides={"scoring": "shared"})
    assert shared.options == expected.replace(scoring="shared", rerank=rerank)


@pytest.mark.parametrize("k", [0, 1, 3])
def test_a_format_3_model_file_with_retrieval_k_loads_as_refine_retrieval(scene, tmp_path, k):
    options = QueryOptions(batch_size=5)
    relocalizer, parts = fitted_with(options, scene, k)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    loaded = load_model(as_format_3(path, tmp_path, k))
    assert loaded.options == options
    if k == 0:
        assert loaded.refiner is None
        return
    assert isinstance(loaded.refiner, RetrievalRefiner) and loaded.refiner.k == k
    # Rebuilt from the index's z-scored descriptors and the map poses: the same answers.
    assert_same_answers(answers(loaded, scene[2]), answers(relocalizer, scene[2]))


def test_an_old_retrieval_model_file_without_map_poses_is_one_data_error(scene, tmp_path):
    relocalizer, parts = fitted_with(QueryOptions(), scene, 1)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    old = as_format_3(path, tmp_path, 2)
    payload = torch.load(old, weights_only=True)
    del payload["map_poses"]
    torch.save(payload, old)
    with pytest.raises(DataError, match=r"damaged model file \(retrieval_k=2 but no map poses"):
        load_model(old)


def test_retrieval_k_is_refused_as_an_override_with_the_new_spelling(scene, tmp_path):
    relocalizer, parts = fitted_with(QueryOptions(), scene)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    with pytest.raises(ConfigError, match="refine=retrieval refine.k=K"):
        load_model(path, overrides={"retrieval_k": 2})


def test_an_old_retrieval_file_with_another_index_is_refused_not_guessed(scene, tmp_path):
    # retrieval_k also ran beside index=faiss, whose state is not z-scored descriptors.
    relocalizer, parts = fitted_with(QueryOptions(), scene, 1)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    old = as_format_3(path, tmp_path, 2)
    payload = torch.load(old, weights_only=True)
    payload["index"]["class"] = "relocfw.plugins.faiss_index.FaissIndex"
    torch.save(payload, old)
    with pytest.raises(DataError, match="reads its retrieval only with index=exhaustive"):
        load_model(old)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("k", torch.tensor(2.7), "refine.k must be an integer"),
        ("k", torch.tensor([1, 2]), "k must be one integer"),
        ("points", None, "points must be a 2-D tensor, got nothing"),
        ("mean", torch.zeros(1), "mean must be a tensor of"),
    ],
)
def test_a_crafted_retrieval_state_is_one_data_error(scene, tmp_path, key, value, message):
    relocalizer, parts = fitted_with(QueryOptions(), scene, 2)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    payload = torch.load(path, weights_only=True)
    payload["refine"]["state"][key] = value
    torch.save(payload, path)
    with pytest.raises(
        DataError, match=rf"model.relocfw: damaged model file \(refine: .*{message}"
    ):
        load_model(path)


def test_nan_in_a_retrieval_state_is_refused_at_load(scene, tmp_path):
    relocalizer, parts = fitted_with(QueryOptions(), scene, 2)
    path = save_model(tmp_path / "model.relocfw", relocalizer, parts, {"scene": "tiny"})
    payload = torch.load(path, weights_only=True)
    payload["refine"]["state"]["points"][0, 0] = float("nan")
    torch.save(payload, path)
    with pytest.raises(DataError, match="points holds NaN or infinite values"):
        load_model(path)
