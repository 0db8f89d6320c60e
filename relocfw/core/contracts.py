"""Contract checks for plugin authors: does my class behave as relocfw expects?

Each function exercises one interface the way the pipeline uses it and raises
AssertionError with a sentence saying which rule broke. Call them from your tests:

    from relocfw.core.contracts import check_crop_search
    def test_my_search_keeps_the_contract():
        check_crop_search(MySearch())
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch

from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex, crop_side_and_span
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.values import Crop, Pose, PoseOutput
from relocfw.core.window_pooling import StripMaps

IMAGE_SIZES = ((640, 480), (160, 120), (300, 400), (97, 64), (100, 100))


class RecordingDistance:
    """A known distance over crop offsets that checks and records every crop it gets."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        _, self.span = crop_side_and_span(width, height)
        self.target = self.span // 3
        self.scored: list[int] = []

    def __call__(self, crops: Sequence[Crop]) -> np.ndarray:
        assert len(crops) > 0, "distance() was called with no crops"
        values = []
        for crop in crops:
            assert isinstance(crop, Crop), f"distance() got {type(crop).__name__}, not Crop"
            check_crop(crop, self.width, self.height)
            offset = crop.x if self.width >= self.height else crop.y
            self.scored.append(offset)
            values.append(abs(offset - self.target) / max(1, self.span) * 10)
        return np.asarray(values)


def check_crop_search(search: CropSearch, sizes: Sequence[tuple[int, int]] = IMAGE_SIZES) -> None:
    """Crops are squares of side min(w, h) inside the image, moved along the long axis;
    the distance function is called with batches of valid crops, each crop at most
    once per search; the same input gives the same crop."""
    assert isinstance(search, CropSearch), "a crop search must subclass relocfw.CropSearch"
    for width, height in sizes:
        distance = RecordingDistance(width, height)
        chosen = search.search(width, height, distance)
        assert isinstance(chosen, Crop), f"search() must return a Crop, got {type(chosen)}"
        check_crop(chosen, width, height)
        assert len(distance.scored) == len(set(distance.scored)), (
            f"{width}x{height}: the same crop was scored twice; cache scored offsets"
        )
        again = search.search(width, height, RecordingDistance(width, height))
        assert again == chosen, f"{width}x{height}: one input gave two crops, {chosen} and {again}"


def check_crop(crop: Crop, width: int, height: int) -> None:
    side, span = crop_side_and_span(width, height)
    assert crop.size == side, f"{width}x{height}: crop side must be {side}, got {crop.size}"
    if width >= height:
        assert crop.y == 0 and 0 <= crop.x <= span, f"{width}x{height}: bad crop {crop}"
    else:
        assert crop.x == 0 and 0 <= crop.y <= span, f"{width}x{height}: bad crop {crop}"


def check_similarity_index(make_index: Callable[[], SimilarityIndex], dim: int = 16) -> None:
    """fit() takes [N, D] descriptors; distance() returns [n] finite non-negative floats,
    smaller for a map descriptor than for a far-away one, the same on a second call."""
    rng = np.random.default_rng(0)
    index = make_index()
    assert isinstance(index, SimilarityIndex), "an index must subclass relocfw.SimilarityIndex"
    train = rng.normal(size=(50, dim))
    index.fit(train)
    queries = np.concatenate([train[:5], train[:5] * 0 + 50.0])
    distances = np.asarray(index.distance(queries))
    assert distances.shape == (10,), f"distance() must return shape [n], got {distances.shape}"
    assert np.all(np.isfinite(distances)) and np.all(distances >= 0), "distances must be >= 0"
    assert np.all(distances[:5] < distances[5:]), "map descriptors must be closer than far ones"
    assert np.allclose(index.distance(queries), distances), "distance() must be deterministic"


def check_backbone(backbone: Backbone) -> None:
    """forward() maps [B, 3, s, s] images in [0, 1] to positions [B, 3], unit quaternions
    [B, 4] and descriptors [B, feature_dim]; training mode is differentiable; with the
    scoring=shared hooks, pooling the maps of a square image gives the same descriptor."""
    assert isinstance(backbone, Backbone), "a backbone must subclass relocfw.Backbone"
    size = int(backbone.input_size)
    images = torch.rand(2, 3, size, size)
    backbone.eval()
    with torch.inference_mode():
        out = backbone(images)
    assert isinstance(out, PoseOutput), "forward() must return relocfw.PoseOutput"
    assert out.positions.shape == (2, 3), f"positions must be [B, 3], got {out.positions.shape}"
    assert out.quaternions.shape == (2, 4), "quaternions must be [B, 4] (w first)"
    assert torch.allclose(out.quaternions.norm(dim=1), torch.ones(2), atol=1e-4), (
        "quaternions must have unit norm"
    )
    assert out.features.shape == (2, backbone.feature_dim), "features must be [B, feature_dim]"
    backbone.train()
    out = backbone(images)
    loss = out.positions.sum() + out.quaternions.sum()
    loss.backward()
    assert any(p.grad is not None for p in backbone.parameters()), "no gradient reached weights"
    backbone.eval()
    check_sampling(backbone, images)
    if backbone.shares_strip:
        # On a square image the one window is the whole image: shared == plain.
        with torch.inference_mode():
            maps = backbone.feature_maps(images)
            pooled = StripMaps(maps[0], size, size, size).pooled([(0, 0)])
            shared = backbone.describe_pooled(pooled)
            plain = backbone(images[:1]).features
        assert torch.allclose(shared, plain, atol=1e-4, rtol=1e-4), (
            "describe_pooled(average of feature_maps) must equal forward()'s features"
        )


def check_sampling(backbone: Backbone, images: torch.Tensor, samples: int = 4) -> None:
    """A backbone that samples at test time (`mc_samples` in test_time_options) answers
    with a mean pose, a spread per image, and the dropout-free descriptor (the index
    must see the same descriptor however many samples are drawn)."""
    if "mc_samples" not in getattr(backbone, "test_time_options", ()):
        return
    configured = backbone.mc_samples
    try:
        with torch.inference_mode():
            backbone.mc_samples = 0
            plain = backbone(images)
            backbone.mc_samples = samples
            sampled = backbone(images)
    finally:
        backbone.mc_samples = configured
    count = len(images)
    for name in ("position_spread", "orientation_spread_deg"):
        spread = getattr(sampled, name)
        assert spread is not None and spread.shape == (count,), f"{name} must be [B] when sampled"
        assert torch.all(torch.isfinite(spread) & (spread >= 0)), f"{name} must be finite, >= 0"
    assert torch.allclose(sampled.quaternions.norm(dim=1), torch.ones(count), atol=1e-4), (
        "the sampled mean quaternion must have unit norm"
    )
    assert torch.allclose(sampled.features, plain.features, atol=1e-5), (
        "sampling must not change the descriptor the index sees (return the dropout-free one)"
    )


def check_refiner(make_refiner: Callable[[], PoseRefiner], dim: int = 8) -> None:
    """A refiner fitted on a small map of two recordings answers every query with a
    `Refined` (finite position, unit quaternion, a float confidence, a bool fell_back,
    seconds per part), leaves the query as it was, answers the same queries the same
    way on a fresh instance whatever queries follow (no state shared between instances,
    no randomness left unseeded), and, where it saves a state, answers the same after
    `load_state(state())` on a fresh instance.

    `make_refiner` builds a fresh, unfitted refiner; queries carry frame names
    ("rec-1/frame-000003") in recording order, as the pipeline sends them."""
    rng = np.random.default_rng(0)
    views, descriptors = [], []
    for recording in range(2):
        for frame in range(8):
            position = np.array([0.1 * frame, float(recording), 0.0])
            angle = 0.05 * frame
            quaternion = np.array([np.cos(angle), 0.0, 0.0, np.sin(angle)])
            image = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
            name = f"rec-{recording}/frame-{frame:06d}"
            views.append(MapImage(name, image, Pose(position, quaternion)))
            descriptors.append(np.concatenate([position, rng.normal(size=dim - 3)]))
    descriptors = np.stack(descriptors)
    queries = [
        RefineQuery(view.image.copy(), view.pose, descriptors[i] + 0.01, name=f"q/{i:06d}")
        for i, view in enumerate(views[:6])
    ]

    def answers(refiner: PoseRefiner, asked: Sequence[RefineQuery]) -> list[Refined]:
        return [refiner.refine(query) for query in asked]

    refiner = make_refiner()
    refiner.fit(views, descriptors, quiet=True)
    first = answers(refiner, queries)
    for i, (query, refined) in enumerate(zip(queries, first, strict=True)):
        assert isinstance(refined, Refined), "refine() must return relocfw.Refined"
        assert np.all(np.isfinite(refined.pose.position)), "the refined position must be finite"
        norm = np.linalg.norm(refined.pose.quaternion)
        assert abs(norm - 1) < 1e-6, "the refined quaternion must have unit norm"
        assert isinstance(refined.confidence, float), "confidence must be a float (NaN: none)"
        assert isinstance(refined.fell_back, bool), "fell_back must be a bool"
        assert all(isinstance(s, float) for s in refined.seconds.values()), "seconds: floats"
        assert np.array_equal(query.descriptor, descriptors[i] + 0.01), (
            "refine() must not change the query's descriptor"
        )
    # Later queries changed: the answers before them must not move.
    changed = queries[:3] + [
        dataclasses.replace(q, descriptor=q.descriptor + 5.0, image=255 - q.image)
        for q in queries[3:]
    ]
    again = make_refiner()
    again.fit(views, descriptors, quiet=True)
    for before, after in zip(first[:3], answers(again, changed)[:3], strict=True):
        assert np.allclose(before.pose.position, after.pose.position, atol=1e-9), (
            "an answer must not depend on the queries after it (nor on what another "
            "instance of the refiner was asked: keep state on the instance)"
        )
    if refiner.saves_state:
        loaded = make_refiner()
        loaded.load_state(refiner.state())
        for before, after in zip(first, answers(loaded, queries), strict=True):
            assert np.allclose(before.pose.position, after.pose.position, atol=1e-6), (
                "a refiner loaded from state() must answer as the fitted one"
            )
