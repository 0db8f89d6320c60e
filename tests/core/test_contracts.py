"""relocfw's own contract checks, run on every built-in (and the example plugin)."""

import dataclasses

import pytest

from relocfw.core.contracts import (
    check_backbone,
    check_crop_search,
    check_refiner,
    check_similarity_index,
)
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.kmeans_index import KMeansIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


@pytest.mark.parametrize(
    "search", [CentreCrop(), SweepCrop(), SweepCrop(stride=7), GeneticCropSearch()]
)
def test_builtin_crop_searches(search):
    check_crop_search(search)


@pytest.mark.parametrize("make", [ExhaustiveIndex, lambda: KMeansIndex(k=5)])
def test_builtin_indexes(make):
    check_similarity_index(make)


@pytest.mark.parametrize("kind", ["flat", "ivf", "hnsw"])
def test_faiss_index(kind):
    pytest.importorskip("faiss")
    from relocfw.plugins.faiss_index import FaissIndex

    check_similarity_index(lambda: FaissIndex(kind=kind, nlist=4, nprobe=4))


@pytest.mark.parametrize("variant", ["head", "kendall", "all"])
def test_posenet_backbone(variant):
    tiny = {"input_size": 32, "width": 0.125, "feature_dim": 16, "dropout_variant": variant}
    check_backbone(PoseNet(**tiny))
    check_backbone(PoseNet(**tiny, mc_samples=4))


def test_a_backbone_whose_sampling_changes_the_descriptor_is_caught():
    class SampledDescriptor(PoseNet):
        def forward(self, images):
            out = super().forward(images)
            if self.mc_samples and not self.training:
                return dataclasses.replace(out, features=out.features + 1.0)
            return out

    backbone = SampledDescriptor(input_size=32, width=0.125, feature_dim=16)
    with pytest.raises(AssertionError, match="sampling must not change the descriptor"):
        check_backbone(backbone)


def test_efficientnet_backbone():
    pytest.importorskip("efficientnet_lite_pytorch")
    from relocfw.plugins.efficientnet_lite import EfficientNetLite0

    check_backbone(EfficientNetLite0(input_size=32, feature_dim=16, pretrained=False))


def test_example_plugin():
    plugin = pytest.importorskip("relocfw_coarse_to_fine.search")
    check_crop_search(plugin.CoarseToFineCrop())


def test_a_broken_search_is_caught():
    class Repeats(CentreCrop):
        def search(self, width, height, distance):
            crop = super().search(width, height, distance)
            distance([crop])
            distance([crop])
            return crop

    with pytest.raises(AssertionError, match="scored twice"):
        check_crop_search(Repeats())


@pytest.mark.parametrize("direction", ["causal", "bidirectional"])
def test_the_sequence_refiner_keeps_the_refiner_contract(direction):
    from relocfw.plugins.sequence_refiner import SequenceRefiner

    check_refiner(lambda: SequenceRefiner(window=3, direction=direction, hidden=8, steps=20))


def test_the_retrieval_refiner_keeps_the_refiner_contract():
    from relocfw.plugins.retrieval_refiner import RetrievalRefiner

    check_refiner(lambda: RetrievalRefiner(k=2))


def test_the_refiner_check_catches_a_refiner_with_global_state():
    from relocfw.core.values import Pose
    from relocfw.plugins.retrieval_refiner import RetrievalRefiner

    class Remembers(RetrievalRefiner):
        """Keeps its history on the class: a second instance answers from the first's
        queries, the kind of state a refiner must not share."""

        history = []

        def refine(self, query):
            self.history.append(query.name)
            found = super().refine(query)
            moved = found.pose.position + 0.1 * len(self.history)
            return dataclasses.replace(found, pose=Pose(moved, found.pose.quaternion))

    with pytest.raises(AssertionError, match="after it"):
        check_refiner(lambda: Remembers(k=1))
