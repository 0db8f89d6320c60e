"""refine.map_store=compact and refine.keyframe_search=faiss (plugins/features_refiner.py).

Each test pins what a plausible slip would break: a compact refiner that answers
from other keyframes or other points than the map in memory (another pose, another
fallback), a faiss search that is not the numpy search (another standardisation,
another order), a compact model file that does not answer as the run or loads a
damaged tensor, and option combinations that cannot work accepted silently.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from relocfw import ConfigError, DataError, MapImage, Pose
from relocfw.core.geometry import orientation_error_deg
from relocfw.core.refinement import RefineQuery
from relocfw.plugins.features_refiner import FeaturesRefiner
from relocfw.structure.compact_cache import compact_folder
from relocfw.structure.compact_map import CompactMap
from tests.structure.conftest import SyntheticScene

pytest.importorskip("poselib")

# The map descriptors keyframes are retrieved by: the query's (below) is nearest view 1,
# then view 0, so retrieval by descriptor picks the two views the query lies between.
MAP_DESCRIPTORS = np.array([[1.0, 0.0, 0.2], [0.8, 0.3, 0.0], [-1.0, 1.0, 1.0]])
QUERY_DESCRIPTOR = np.array([0.85, 0.25, 0.05])
OPTIONS = {"count": 2, "max_features": 1024, "quiet": True}


def map_images(scene: SyntheticScene) -> list[MapImage]:
    """The scene's three views with their depth PNGs."""
    return [MapImage(v.name, v.image, v.pose, v.camera, v.depth_path) for v in scene.views]


def network_guess(scene: SyntheticScene) -> Pose:
    """A network's pose 30 cm off the truth: a fallback is told apart from a solve."""
    truth = scene.query_pose
    return Pose(truth.position + [0.3, 0.0, 0.0], truth.quaternion)


def queries(scene: SyntheticScene) -> list[RefineQuery]:
    """Two frames of one recording (keyframes=track uses the first's pose for the
    second), then a blank one that cannot be solved (no texture, no keypoint)."""
    guess = network_guess(scene)
    blank = np.full_like(scene.query_image, 128)
    return [
        RefineQuery(scene.query_image, guess, QUERY_DESCRIPTOR, name="seq/0"),
        RefineQuery(scene.query_image, guess, QUERY_DESCRIPTOR, name="seq/1"),
        RefineQuery(blank, guess, QUERY_DESCRIPTOR, name="seq/2"),
    ]


def fitted(scene: SyntheticScene, cache_dir: Path, **options) -> FeaturesRefiner:
    options = {**OPTIONS, **options}
    refiner = FeaturesRefiner(cache_dir=cache_dir, **options)
    refiner.fit(map_images(scene), MAP_DESCRIPTORS, quiet=options["quiet"])
    return refiner


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("compact_cache")


def assert_same_answers(got: list, expected: list, metres: float, degrees: float) -> None:
    """Same fallbacks and inlier counts (other keyframes give other counts: 688 inliers
    with views 0 and 1, 654 with 1 and 2), poses within the bounds."""
    for a, b in zip(got, expected, strict=True):
        assert a.fell_back == b.fell_back
        assert a.confidence == b.confidence
        assert np.linalg.norm(a.pose.position - b.pose.position) <= metres
        assert orientation_error_deg(a.pose.quaternion, b.pose.quaternion) <= degrees


@pytest.mark.parametrize(
    "keyframes, rematch",
    [("descriptor", "none"), ("pose", "none"), ("track", "none"), ("pose", "union")],
)
def test_a_compact_map_answers_as_the_map_in_memory(synthetic_scene, cache_dir, keyframes, rematch):
    # rematch=union: the compact store renumbers a query's keyframes; the union must
    # still be of map indices (here views 1, 2 near the network's pose, then 1, 0 near
    # the answer: a second solve over all three).
    memory = fitted(synthetic_scene, cache_dir, keyframes=keyframes, rematch=rematch)
    compact = fitted(
        synthetic_scene, cache_dir, keyframes=keyframes, map_store="compact", rematch=rematch
    )
    # The compact refiner holds no StructureMap: its map is the mapped folder.
    assert compact.structure is None and isinstance(compact.compact, CompactMap)
    assert compact.compact.folder.parent == cache_dir / "structure"
    expected = [memory.refine(q) for q in queries(synthetic_scene)]
    got = [compact.refine(q) for q in queries(synthetic_scene)]
    assert [a.fell_back for a in expected] == [False, False, True]  # solves, and a fallback
    truth = synthetic_scene.query_pose.position
    assert np.linalg.norm(expected[0].pose.position - truth) < 0.01
    assert_same_answers(got, expected, metres=1e-3, degrees=0.1)
    assert compact.keyframes_of(queries(synthetic_scene)[0]) == memory.keyframes_of(
        queries(synthetic_scene)[0]
    )
    if rematch == "union":
        assert "rematch" in got[0].seconds and "rematch" in expected[0].seconds
        assert got[0].seconds["solve"] > 0 and got[0].confidence == expected[0].confidence


def test_the_compact_folder_is_written_once_and_reused(synthetic_scene, cache_dir, capsys):
    first = fitted(synthetic_scene, cache_dir, map_store="compact", quiet=False)
    folder = first.compact.folder
    written = (folder / "codes.npy").stat().st_mtime_ns
    second = fitted(synthetic_scene, cache_dir, map_store="compact", quiet=False)
    assert second.compact.folder == folder
    assert (folder / "codes.npy").stat().st_mtime_ns == written
    assert f"reused compact {folder}" in capsys.readouterr().err
    # A damaged folder is rewritten, not read.
    (folder / "map.json").write_text("{")
    third = fitted(synthetic_scene, cache_dir, map_store="compact")
    assert "rewriting it" in capsys.readouterr().err
    assert len(CompactMap.open(folder)) == len(third.compact) == 3


def test_faiss_keyframes_are_numpys(synthetic_scene, cache_dir):
    pytest.importorskip("faiss")
    numpy_search = fitted(synthetic_scene, cache_dir, count=3)
    faiss_search = fitted(synthetic_scene, cache_dir, count=3, keyframe_search="faiss")
    assert faiss_search.keyframe_index is not None and numpy_search.keyframe_index is None
    rng = np.random.default_rng(0)
    for descriptor in [QUERY_DESCRIPTOR, *rng.normal(size=(20, 3))]:
        query = RefineQuery(synthetic_scene.query_image, network_guess(synthetic_scene), descriptor)
        assert faiss_search.keyframes_of(query) == numpy_search.keyframes_of(query)
    assert faiss_search.keyframes_of(queries(synthetic_scene)[0]) == [1, 0, 2]


def test_a_saved_compact_refiner_answers_as_the_run(synthetic_scene, cache_dir, tmp_path):
    refiner = fitted(synthetic_scene, cache_dir, keyframes="track", map_store="compact")
    expected = [refiner.refine(q) for q in queries(synthetic_scene)]
    refiner.reset()
    path = tmp_path / "state.pt"
    torch.save(refiner.state(), path)
    # Loaded elsewhere: the cache is gone, and the constructor's options are memory's.
    loaded = FeaturesRefiner(quiet=True)
    loaded.load_state(torch.load(path, weights_only=True))
    assert (loaded.map_store, loaded.keyframes, loaded.count) == ("compact", "track", 2)
    assert loaded.compact.folder is None  # over the file's arrays, not a folder
    assert_same_answers([loaded.refine(q) for q in queries(synthetic_scene)], expected, 0.0, 0.0)


def test_a_file_without_the_new_options_loads_as_memory_and_numpy(synthetic_scene, cache_dir):
    state = fitted(synthetic_scene, cache_dir).state()
    del state["map_store"], state["keyframe_search"]
    loaded = FeaturesRefiner(quiet=True)
    loaded.load_state(state)
    assert (loaded.map_store, loaded.keyframe_search) == ("memory", "numpy")
    assert loaded.compact is None and loaded.structure is not None


@pytest.fixture(scope="module")
def compact_state(synthetic_scene, cache_dir) -> dict:
    return fitted(synthetic_scene, cache_dir, map_store="compact").state()


def damaged(state: dict, key: str, how: str) -> dict:
    state = {name: value.clone() for name, value in state.items()}
    if how == "dtype":
        state[key] = state[key].double()
    elif how == "missing":
        del state[key]
    elif how == "nan":
        state[key].view(-1)[0] = float("nan")
    elif how == "value":
        state[key].view(-1)[-1] = state[key].view(-1)[-1] + 7
    elif how == "zero":
        state[key] = torch.zeros_like(state[key])
    return state


@pytest.mark.parametrize(
    ("key", "how", "message"),
    [
        ("compact_codes", "dtype", "compact_codes must be torch.uint8"),
        ("compact_points", "nan", "compact_points hold values that are not finite"),
        ("compact_offsets", "value", "compact_offsets: offsets must rise"),
        ("compact_poses", "nan", "compact_poses: a pose is not finite"),
        ("compact_cameras", "missing", "compact_cameras must be a tensor, got nothing"),
        ("compact_names", "dtype", "compact_names must be torch.uint8"),
        ("compact_source", "value", "compact_source must be one of"),
        ("compact_format", "value", "compact_format is 8"),
        ("compact_rows", "value", "compact_codes holds uint8"),
        ("map_store", "value", "map_store must be in 0..1"),
        ("compact_images", "zero", "compact_images is 0: the map holds no image"),
    ],
)
def test_a_damaged_compact_tensor_is_one_data_error_naming_it(compact_state, key, how, message):
    loaded = FeaturesRefiner(quiet=True)
    with pytest.raises(DataError, match=message) as caught:
        loaded.load_state(damaged(compact_state, key, how))
    assert str(caught.value).startswith("refine=features state: ")
    assert "\n" not in str(caught.value)
    assert loaded.structure is None and loaded.compact is None  # nothing was kept


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            {"map_store": "compact", "match_points_only": False, "cache_dir": "c"},
            "refine.map_store=compact .* refine.match_points_only=true",
        ),
        ({"map_store": "compact"}, "refine.map_store=compact .* needs a cache_dir"),
        ({"map_store": "disk"}, "refine.map_store must be one of memory, compact, got 'disk'"),
        ({"keyframe_search": "annoy"}, "refine.keyframe_search must be one of numpy, faiss"),
    ],
)
def test_a_bad_store_or_search_option_is_one_config_error_naming_it(options, message):
    with pytest.raises(ConfigError, match=message):
        FeaturesRefiner(**options)


def test_faiss_missing_is_a_config_error_saying_how_to_install_it(monkeypatch):
    import importlib

    real = importlib.import_module

    def without_faiss(name, *args):
        if name == "faiss":
            raise ImportError("No module named 'faiss'")
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", without_faiss)
    with pytest.raises(ConfigError, match=r'keyframe_search=faiss .*pip install -e "\.\[faiss\]"'):
        FeaturesRefiner(keyframe_search="faiss")


def test_the_compact_folder_sits_beside_the_cache_entry(tmp_path):
    assert compact_folder(tmp_path, "0123abcd") == tmp_path / "structure" / "0123abcd.compact"
