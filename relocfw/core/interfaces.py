"""The plugin interfaces. Implementations live in plugins/ or in other packages."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Generator, Mapping, Sequence
from functools import cached_property
from typing import ClassVar

import numpy as np
import torch

from relocfw.core.values import Crop, PoseOutput

CropDistance = Callable[[Sequence[Crop]], np.ndarray]
"""Scores a batch of crops in one forward pass: [n] distances to the map, lower is closer.

The pipeline's distance also carries `query_seed`, an integer fingerprint of the query
image; read it with `query_seed(distance)`.
"""

CropProposals = Generator[Sequence[Crop], np.ndarray, Crop]
"""A crop search in ask/tell form: yields batches of crops, is sent their distances.

`values = yield crops` asks for the [n] map distances of n crops (lower is closer);
`return crop` names the chosen one. The pipeline drives many queries' proposals in
one loop, their crops in merged forward passes (`CropSearch.propose`).
"""


class CropScores(np.ndarray):
    """What a search that sees answers (`CropSearch.sees_answers`) is sent for n crops:
    their [n] distances, as the array itself, so it reads like any other search's
    values, with each crop's network answer beside them.

    Attributes:
        positions: [n, 3] each crop's regressed position.
        quaternions: [n, 4] its orientation (w, x, y, z).
        features: [n, D] its dropout-free descriptor (comparable with the map's).
    """

    positions: np.ndarray
    quaternions: np.ndarray
    features: np.ndarray

    @classmethod
    def of(
        cls,
        distances: np.ndarray,
        positions: np.ndarray,
        quaternions: np.ndarray,
        features: np.ndarray,
    ) -> CropScores:
        scores = np.asarray(distances, dtype=np.float64).view(cls)
        scores.positions = np.asarray(positions, dtype=np.float64)
        scores.quaternions = np.asarray(quaternions, dtype=np.float64)
        scores.features = np.asarray(features, dtype=np.float64)
        return scores


def query_seed(distance: CropDistance) -> int:
    """Seed material of the query being searched, for searches that draw random numbers.

    Mix it with the search's own seed (e.g. `np.random.default_rng([seed,
    query_seed(distance)])`): every query then gets its own stream, so the queries of a
    test split are independent runs, while the same image still gives the same crop.
    0 when the caller's `distance` is a plain function that carries none.
    """
    return int(getattr(distance, "query_seed", 0))


class SearchQuery:
    """What a crop search knows of its query: the image's size and its seed.

    Args:
        width, height: the query image's size in pixels; the square crop's side is
            min(width, height) and it slides along the longer axis.
        seed_of: returns the query's seed material (a fingerprint of the image); called
            at most once, when a search first reads `seed`, because hashing a
            full-resolution image costs milliseconds that centre and sweep need not pay.
    """

    def __init__(self, width: int, height: int, seed_of: Callable[[], int] = lambda: 0):
        self.width = int(width)
        self.height = int(height)
        self._seed_of = seed_of

    @cached_property
    def seed(self) -> int:
        """Mix with the search's own seed (`np.random.default_rng([seed, query.seed])`):
        each query gets its own stream, and the same image the same crop."""
        return int(self._seed_of())


def drive(proposals: CropProposals, distance: CropDistance) -> Crop:
    """Run one query's proposals to its crop, each batch scored by `distance`."""
    try:
        crops = next(proposals)
        while True:
            crops = proposals.send(distance(crops))
    except StopIteration as end:
        return end.value


class Backbone(torch.nn.Module, ABC):
    """Image batch -> pose and descriptor.

    Inputs are float tensors [B, 3, input_size, input_size], RGB in [0, 1]; the backbone
    owns its own normalisation so weights and preprocessing cannot drift apart.

    Positions are regressed in a normalised frame (training positions minus their mean,
    divided by their spread) and mapped back here, because a network regresses values
    near zero with unit spread far better than raw world coordinates. The statistics are
    buffers, so they travel with the checkpoint.
    """

    input_size: int
    feature_dim: int
    # Constructor options that only change inference (e.g. Monte Carlo samples): they
    # are left out of the checkpoint key, so such variants share one trained model.
    test_time_options: tuple[str, ...] = ()
    # Options left out of the checkpoint key while they hold these values: an option
    # added after models were trained, whose default is what those models are, keeps
    # their key (and their cached checkpoints).
    key_defaults: ClassVar[Mapping[str, object]] = {}
    # Options replaced when a saved model is rebuilt: its state already holds the
    # weights, so e.g. an ImageNet weights file is not needed (or read) again.
    rebuild_overrides: dict[str, object] = {}
    # Run inference in channels-last memory layout: on CPU it makes GoogLeNet's
    # convolutions and poolings about 1.5x faster for one image (benchmarks/). A
    # backbone whose forward needs contiguous NCHW tensors (e.g. `.view`) sets False.
    channels_last: bool = True
    # The share of one dropout-free forward pass's work that each Monte Carlo sample
    # reruns (the layers from the first dropout up), for `network_passes`. None: measured
    # from the multiply-adds of the backbone's own passes (relocfw.core.sampling.
    # sample_share); declare it where most of the work is not in Conv / Linear layers.
    sample_share: float | None = None
    # True when the weights start from training elsewhere (e.g. ImageNet): settings
    # that only fine-tune (preset=paper's lr 1e-5) refuse a backbone without it.
    pretrained: bool = False

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("position_mean", torch.zeros(3))
        self.register_buffer("position_scale", torch.ones(()))
        # The field of view of the training crops (TrainSettings.crop_scale): the
        # pipeline shows the network the central 1/crop_scale of every query crop.
        self.register_buffer("crop_scale", torch.ones(()))

    def set_position_normalisation(self, mean: np.ndarray, scale: float) -> None:
        """Fix the frame positions are regressed in; call once before training."""
        self.position_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.position_scale.fill_(float(scale))

    def set_crop_scale(self, crop_scale: float) -> None:
        """Record the training crops' crop_scale; training calls it."""
        self.crop_scale.fill_(float(crop_scale))

    def to_world_positions(self, normalised: torch.Tensor) -> torch.Tensor:
        """Map the network's raw position output to metres in the world frame."""
        return normalised * self.position_scale + self.position_mean

    @abstractmethod
    def forward(self, images: torch.Tensor) -> PoseOutput:
        """Pose and descriptor of each image in the batch."""

    # Optional pair of hooks for scoring=shared (see relocfw.core.window_pooling): a backbone
    # whose descriptor is a layer on the global average of its last convolutional maps
    # can describe every crop window of a strip from ONE pass over the whole strip.
    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        """[B, C, h, w] last convolutional maps of inputs of any size, before pooling."""
        raise NotImplementedError(f"{type(self).__name__} has no feature_maps")

    def describe_pooled(self, pooled: torch.Tensor) -> torch.Tensor:
        """[n, D] descriptors from [n, C] average-pooled `feature_maps`."""
        raise NotImplementedError(f"{type(self).__name__} has no describe_pooled")

    # Optional hook for scoring=scout (see relocfw.core.query_windows): a cheaper,
    # approximate copy of the network (engine=onnx with onnx.int8: the int8 graph)
    # ranks the candidate crops; the chosen crop's answer still comes from `forward`.
    def scout_features(self, images: torch.Tensor) -> torch.Tensor:
        """[B, D] the scout's descriptors of the images; without a cheaper copy, the
        network's own (scoring=scout then chooses what scoring=plain does)."""
        return self(images).features

    def scout_refusal(self) -> str | None:
        """Why scoring=scout cannot run on this backbone as documented (its chosen
        crop answered at full precision); None: it can."""
        return None

    @property
    def shares_strip(self) -> bool:
        """True when both optional hooks are provided (scoring=shared is possible)."""
        cls = type(self)
        return (
            cls.feature_maps is not Backbone.feature_maps
            and cls.describe_pooled is not Backbone.describe_pooled
        )


class SimilarityIndex(ABC):
    """The map: training descriptors, queried for how far a descriptor is from it."""

    @abstractmethod
    def fit(self, features: np.ndarray) -> None:
        """Build the map from [N, D] training descriptors."""

    @abstractmethod
    def distance(self, features: np.ndarray) -> np.ndarray:
        """[n] distance of each of [n, D] descriptors to the map; lower = more similar."""

    def state(self) -> dict[str, torch.Tensor]:
        """The fitted map as tensors, for model files; optional for plugins."""
        raise NotImplementedError(f"{type(self).__name__} cannot be saved in a model file")

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore what `state` returned."""
        raise NotImplementedError(f"{type(self).__name__} cannot be loaded from a model file")

    def check_map_size(self, count: int) -> None:  # noqa: B027 - optional hook, no-op default
        """Raise ConfigError if a map of `count` descriptors cannot be built.

        Called before training, so an impossible option (k-means with more clusters
        than images) fails in a second rather than after the model is trained.
        """


class CropSearch(ABC):  # noqa: B024 - one of two methods, checked in __new__
    """Chooses the square crop of a width x height image whose descriptor is closest.

    The square's side is min(width, height); a search moves it along the longer axis.
    A search defines `propose` (ask/tell: the pipeline batches many queries' crops
    into one forward pass per round) or, the older form, `search` (one query at a
    time, blocking inside `distance`); each is available from the other.

    Example:
        >>> class LeftEdge(CropSearch):
        ...     def propose(self, query):
        ...         crops = [crop_at(0, query.width, query.height)]
        ...         distances = yield crops
        ...         return crops[int(np.argmin(distances))]
        >>> LeftEdge().search(8, 4, lambda crops: np.zeros(len(crops)))
        Crop(x=0, y=0, size=4)
    """

    # True for a search that chooses by what the network answers for each crop, not by
    # distance alone (e.g. agreement of poses): it is sent CropScores. It needs every
    # crop's answer, so it runs with plain scoring only.
    sees_answers: ClassVar[bool] = False
    # True for a search that needs the map itself: `fit_map` is then called by
    # Relocalizer.fit with the map images' descriptors and poses.
    wants_map: ClassVar[bool] = False

    def fit_map(  # noqa: B027 - optional hook, no-op default
        self, descriptors: np.ndarray, poses: Sequence[object], distance_scale: float
    ) -> None:
        """Learn what the search needs of the map (searches with `wants_map`).

        Args:
            descriptors: [N, D] the map images' centre-crop descriptors.
            poses: their relocfw Poses, in the same order.
            distance_scale: the map images' own median map distance, a unit that makes
                distances comparable across models.
        """

    def __new__(cls, *args: object, **kwargs: object) -> CropSearch:
        if cls.propose is CropSearch.propose and cls.search is CropSearch.search:
            raise TypeError(
                f"Can't instantiate {cls.__name__}: a CropSearch defines propose(query) "
                "(or the older search(width, height, distance))"
            )
        return super().__new__(cls)

    def propose(self, query: SearchQuery) -> CropProposals:
        """Ask for crops' distances (`values = yield crops`), then `return` the crop.

        Shape:
            each yield: a sequence of n crops; what comes back: [n] float distances.

        Ask for each crop once: the pipeline never scores a window twice for a
        query, but a batch of already-known crops still costs a round. Keep
        per-query state in the generator's locals and draw random numbers from
        `np.random.default_rng([own seed, query.seed])`, never a global generator.
        """
        raise NotImplementedError(f"{type(self).__name__} defines only search")

    def search(self, width: int, height: int, distance: CropDistance) -> Crop:
        """Return the chosen crop; `distance` scores many crops per call.

        The older, blocking form, kept for searches written against it: the pipeline
        runs such a search one query at a time. A search that defines `propose` gets
        this from it. A search that draws random numbers seeds them from its own seed
        and `query_seed(distance)`, so each query is searched independently.
        """
        query = SearchQuery(width, height, lambda: query_seed(distance))
        return drive(self.propose(query), distance)

    @property
    def asks_and_tells(self) -> bool:
        """True when the search defines `propose`, so queries can be searched together."""
        return type(self).propose is not CropSearch.propose


def crop_side_and_span(width: int, height: int) -> tuple[int, int]:
    """Square side and how far it can slide along the longer axis."""
    side = min(width, height)
    return side, max(width, height) - side


def crop_at(offset: int, width: int, height: int) -> Crop:
    """The square crop at `offset` pixels along the longer axis."""
    side = min(width, height)
    return Crop(offset, 0, side) if width >= height else Crop(0, offset, side)
