"""index=faiss: flat equals the exhaustive index; options, saving and bad input."""

import numpy as np
import pytest

from relocfw import ConfigError, DataError, Relocalizer
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.sweep_crop import SweepCrop

faiss = pytest.importorskip("faiss", reason="faiss-cpu not installed (relocfw[faiss])")
from relocfw.plugins.faiss_index import FaissIndex  # noqa: E402 - needs faiss


@pytest.fixture(scope="module")
def descriptors():
    rng = np.random.default_rng(0)
    # Clustered like image descriptors, with per-dimension offsets and scales that the
    # z-scoring must remove, and one dead unit (constant zero).
    centres = rng.normal(size=(20, 64)) * 3
    map_points = centres[rng.integers(0, 20, 2000)] + rng.normal(size=(2000, 64))
    map_points = map_points * rng.uniform(0.1, 5, 64) + rng.uniform(-3, 3, 64)
    map_points[:, 7] = 0.0
    queries = map_points[rng.integers(0, 2000, 200)] + rng.normal(size=(200, 64)) * 0.5
    return map_points, queries


def test_flat_equals_exhaustive(descriptors):
    map_points, queries = descriptors
    exact = ExhaustiveIndex()
    exact.fit(map_points)
    flat = FaissIndex(kind="flat")
    flat.fit(map_points.astype(np.float32))
    want_d, want_i = exact.neighbours(queries, 3)
    got_d, got_i = flat.neighbours(queries, 3)
    assert np.array_equal(got_i, want_i)
    assert np.allclose(got_d, want_d, rtol=1e-4)
    assert np.allclose(flat.distance(queries), want_d[:, 0], rtol=1e-4)


@pytest.mark.parametrize(
    "options, least_recall",
    [
        ({"kind": "ivf", "nlist": 32, "nprobe": 8}, 0.9),
        ({"kind": "hnsw", "hnsw_m": 16, "ef_search": 64}, 0.9),
        ({"kind": "flat", "precision": "float16"}, 0.99),
        ({"kind": "flat", "pca_dim": 32}, 0.8),
    ],
)
def test_approximate_options_find_most_true_neighbours(descriptors, options, least_recall):
    map_points, queries = descriptors
    exact = ExhaustiveIndex()
    exact.fit(map_points)
    index = FaissIndex(**options)
    index.fit(map_points)
    recall = np.mean(index.neighbours(queries, 1)[1][:, 0] == exact.nearest(queries)[1])
    assert recall >= least_recall


def test_memory_per_descriptor_follows_precision(descriptors):
    map_points, _ = descriptors
    sizes = {}
    for precision in ("float32", "float16"):
        index = FaissIndex(precision=precision)
        index.fit(map_points)
        sizes[precision] = index.bytes_per_descriptor
    assert sizes["float32"] == pytest.approx(64 * 4, rel=0.05)
    assert sizes["float16"] == pytest.approx(64 * 2, rel=0.05)


@pytest.mark.parametrize("kind", ["flat", "ivf", "hnsw"])
def test_saved_state_searches_the_same(descriptors, kind):
    map_points, queries = descriptors
    index = FaissIndex(kind=kind, nlist=16)
    index.fit(map_points)
    restored = FaissIndex(kind=kind, nlist=16)
    restored.load_state(index.state())
    assert np.array_equal(restored.neighbours(queries, 2)[1], index.neighbours(queries, 2)[1])


@pytest.mark.parametrize(
    "options",
    [
        {"kind": "flat"},
        {"kind": "flat", "precision": "float16"},
        {"kind": "ivf", "nlist": 16, "nprobe": 4},
        {"kind": "flat", "pca_dim": 16},
    ],
)
def test_fitting_in_many_chunks_builds_the_same_index(descriptors, options):
    map_points, queries = descriptors
    whole = FaissIndex(**options, rows_at_a_time=len(map_points))
    whole.fit(map_points.astype(np.float32))
    chunked = FaissIndex(**options, rows_at_a_time=300)  # six chunks of 300 and one of 200
    chunked.fit(map_points.astype(np.float32))
    assert chunked.index.ntotal == whole.index.ntotal == len(map_points)
    assert np.allclose(chunked.zscore.mean, whole.zscore.mean, rtol=1e-12, atol=1e-12)
    assert np.allclose(chunked.zscore.std, whole.zscore.std, rtol=1e-12, atol=0)
    # The mean may differ in its last bit (another summation order), so distances
    # agree to float32 rounding rather than bit for bit.
    want_d, want_i = whole.neighbours(queries, 3)
    got_d, got_i = chunked.neighbours(queries, 3)
    assert np.array_equal(got_i, want_i)
    assert np.allclose(got_d, want_d, rtol=1e-5, atol=0)


def test_sweep_with_faiss_flat_answers_as_with_exhaustive(tiny_scene):
    from relocfw.data.frames import read_images
    from relocfw.data.sevenscenes import load_sevenscenes
    from tests.core.test_shared_scoring import tiny_posenet

    train = read_images(load_sevenscenes(tiny_scene, None, "train"), quiet=True)
    test = read_images(load_sevenscenes(tiny_scene, None, "test"), quiet=True)
    answers = {}
    for name, index in (("exhaustive", ExhaustiveIndex()), ("faiss", FaissIndex())):
        relocalizer = Relocalizer(tiny_posenet(), index, SweepCrop())
        relocalizer.fit(train)
        answers[name] = [relocalizer.localize(image) for image in test]
    for a, b in zip(answers["exhaustive"], answers["faiss"], strict=True):
        assert a.crop == b.crop
        assert np.allclose(a.pose.position, b.pose.position)
        assert a.distance == pytest.approx(b.distance, rel=1e-4)


def test_bad_options_and_input_are_named():
    with pytest.raises(ConfigError, match="index.kind must be one of flat, ivf, hnsw"):
        FaissIndex(kind="lsh")
    with pytest.raises(ConfigError, match="index.precision"):
        FaissIndex(precision="int8")
    with pytest.raises(ConfigError, match="nlist=1024 is more IVF cells than map descriptors"):
        FaissIndex(kind="ivf").check_map_size(300)
    index = FaissIndex()
    with pytest.raises(DataError, match="not fitted"):
        index.distance(np.zeros((1, 4)))
    with pytest.raises(DataError, match="NaN"):
        index.fit(np.full((3, 4), np.nan))
    index.fit(np.random.default_rng(0).normal(size=(10, 4)))
    with pytest.raises(DataError, match="descriptors have 5 dimensions, the map has 4"):
        index.distance(np.zeros((1, 5)))
