"""One query through the pipeline: the search's state, then the answer.

`Relocalizer.localize` runs one QueryRun at a time; `Relocalizer.localize_many` runs
several side by side and scores their plain windows together (relocfw.core.lockstep).
Either way a query's choice depends only on its own windows' answers.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from relocfw.core.imaging import Strip, image_fingerprint
from relocfw.core.network_answers import NetworkAnswers
from relocfw.core.sampling import configured_samples
from relocfw.core.values import Crop, Localization
from relocfw.core.window_pooling import StripMaps

if TYPE_CHECKING:
    from relocfw.core.pipeline import Relocalizer

Corner = tuple[int, int]
# Scores plain windows of a strip: their map distances and network answers.
PlainScorer = Callable[[Strip, list[Corner]], tuple[np.ndarray, NetworkAnswers]]


class QueryRun:
    """A query's strip and every window scored for it, each scored once.

    Args:
        relocalizer: the pipeline (network, index, crop search, options).
        image: the query, H x W x 3 uint8 RGB.
        score_plain: scores new plain windows; the relocalizer's own, or a lockstep
            batcher's that scores many queries' windows in one forward pass.
        on_network: runs a piece of network work (shared scoring's passes) and returns
            its result; by default here, in localize_many on the lockstep's serving
            thread.
    """

    def __init__(
        self,
        relocalizer: Relocalizer,
        image: np.ndarray,
        score_plain: PlainScorer,
        on_network: Callable[[Callable[[], Any]], Any] | None = None,
    ):
        self.started = time.perf_counter()
        self.relocalizer = relocalizer
        self.image = image
        self.score_plain = score_plain
        self.on_network = on_network or (lambda work: work())
        backbone = relocalizer.backbone
        self.strip = Strip(image, backbone.input_size, relocalizer.crop_scale)
        # Offsets that round to the same strip window are the same network input:
        # everything is kept per window, so a window is computed once.
        self.results: dict[Corner, tuple[float, NetworkAnswers]] = {}
        self.shared: dict[Corner, float] = {}  # scoring=shared: window -> distance
        self.strip_maps: StripMaps | None = None  # built on the first shared score
        self.crop_of: dict[Corner, Crop] = {}  # a crop for every window scored
        self.chosen: Crop | None = None

    @cached_property
    def query_seed(self) -> int:
        """The image's fingerprint (relocfw.core.interfaces.query_seed), computed when read:
        hashing a full-resolution image costs 1-7 ms that centre and sweep need not pay."""
        return image_fingerprint(self.image)

    def evaluate(self, corners: Sequence[Corner]) -> None:
        new = list(dict.fromkeys(c for c in corners if c not in self.results))
        if not new:
            return
        distances, answers = self.score_plain(self.strip, new)
        for i, corner in enumerate(new):
            self.results[corner] = (float(distances[i]), answers.row(i))

    def score_shared(self, corners: Sequence[Corner]) -> None:
        new = list(dict.fromkeys(c for c in corners if c not in self.shared))
        if not new:
            return

        def distances_of_new() -> np.ndarray:
            if self.strip_maps is None:
                self.strip_maps = self.relocalizer._strip_maps(self.strip)
            features = self.relocalizer._shared_features(self.strip_maps, new)
            return self.relocalizer._map_distance(features)

        distances = self.on_network(distances_of_new)
        self.shared.update(zip(new, (float(d) for d in distances), strict=True))

    def distance(self, crops: Sequence[Crop]) -> np.ndarray:
        """The CropDistance the search gets (it also carries `query_seed`)."""
        corners = [self.strip.window(c) for c in crops]
        for corner, crop in zip(corners, crops, strict=True):
            self.crop_of.setdefault(corner, crop)
        if self.relocalizer.scoring == "shared":
            self.score_shared(corners)
            return np.array([self.shared[c] for c in corners])
        self.evaluate(corners)
        return np.array([self.results[c][0] for c in corners])

    def __call__(self, crops: Sequence[Crop]) -> np.ndarray:
        return self.distance(crops)

    def choose(self) -> Crop:
        """Run the crop search (and the re-scoring of shared candidates) to its crop;
        the chosen window's plain answer is computed here too."""
        relocalizer = self.relocalizer
        chosen = relocalizer.crop.search(self.strip.width, self.strip.height, self)
        corner = self.strip.window(chosen)
        if relocalizer.rerank > 1 and self.shared:
            # The shared distances only rank: the best `rerank` windows go through the
            # plain network in one batch and the plain distance chooses among them.
            # The search's own choice is always among them.
            ranked = sorted(self.shared, key=self.shared.__getitem__)
            candidates = list(dict.fromkeys([corner, *ranked]))[: relocalizer.rerank]
            self.evaluate(candidates)
            best = min(candidates, key=lambda c: self.results[c][0])
            if best != corner:
                corner, chosen = best, self.crop_of[best]
        self.evaluate([corner])
        self.chosen = chosen
        return chosen

    def answer(self, seconds: float | None = None) -> Localization:
        """The Localization of the chosen crop, sampled if the pipeline samples.

        Args:
            seconds: the query's time, when the caller measures it (localize_many
                shares a batch's time among its queries); default: since creation.
        """
        if self.chosen is None:
            raise RuntimeError("QueryRun.answer before choose")
        relocalizer = self.relocalizer
        corner = self.strip.window(self.chosen)
        distance, answer = self.results[corner]
        sampled_passes = 0.0
        if relocalizer.crop_samples > 0 or configured_samples(relocalizer.backbone) > 0:
            answer, sampled_passes = relocalizer._sampled_answer(
                self.strip, self.chosen, answer, self.query_seed
            )
        pose = relocalizer._answer_pose(answer)
        # Cost in whole-network passes: each plain window is one; the strip pass costs
        # its area over a window's (the trunk dominates the network's work); sampling
        # adds what its samples rerun (Relocalizer._sampled_passes).
        side = relocalizer.backbone.input_size
        strip_passes = self.strip.pixels.shape[1] * self.strip.pixels.shape[2] / side**2
        if seconds is None:
            seconds = time.perf_counter() - self.started
        return Localization(
            pose=pose,
            crop=self.chosen,
            distance=distance,
            evaluations=len(set(self.results) | set(self.shared)),
            seconds=seconds,
            position_spread=float(answer.position_spread),
            orientation_spread_deg=float(answer.orientation_spread_deg),
            network_passes=len(self.results)
            + sampled_passes
            + (0.0 if self.strip_maps is None else strip_passes),
        )
