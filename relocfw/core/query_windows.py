"""One query's strip and every window scored for it, each scored once.

A crop search asks for crops; offsets that round to the same strip window are the
same network input, so everything is kept per window and a window is computed once
(`evaluations` counts the distinct windows scored). The query's two limits are
checked here, so they hold for every crop search: its shape (query.max_aspect) before
the strip is built, and the distinct windows its search asks for
(query.max_candidates) before any of them is scored.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import cached_property

import numpy as np

from relocfw.core.errors import DataError
from relocfw.core.imaging import MAX_ASPECT, check_aspect, image_fingerprint
from relocfw.core.interfaces import CropScores, SearchQuery
from relocfw.core.network_answers import NetworkAnswers
from relocfw.core.query_options import MAX_CANDIDATES
from relocfw.core.scorer import Corner, Scorer
from relocfw.core.values import Crop
from relocfw.core.window_pooling import StripMaps


class QueryWindows:
    """A query's windows: their plain answers and, with scoring=shared or scout, the
    distances that only rank candidates (`ranking`).

    Args:
        image: the query, H x W x 3 uint8 RGB (checked by the caller).
        scorer: the network and the map.
        scoring: "plain", "shared" or "scout" (relocfw.core.query_options.QueryOptions).
        max_aspect, max_candidates: the query's limits (QueryOptions' fields).

    Raises:
        DataError: naming query.max_aspect, for an image thinner than it allows (or
            one whose strip cannot be allocated); naming query.max_candidates, from
            `corners`, when a search asks for more distinct windows.

    Calling it with crops is the query's CropDistance (it also carries `query_seed`),
    what the older `CropSearch.search` form is given.
    """

    def __init__(
        self,
        image: np.ndarray,
        scorer: Scorer,
        scoring: str = "plain",
        max_aspect: float = MAX_ASPECT,
        max_candidates: int = MAX_CANDIDATES,
    ) -> None:
        self.started = time.perf_counter()
        check_aspect(image.shape[1], image.shape[0], "the query image is", max_aspect)
        self.image = image
        self.scorer = scorer
        self.scoring = scoring
        self.max_candidates = max_candidates
        self.strip = scorer.strip(image)
        self.plain: dict[Corner, tuple[float, NetworkAnswers]] = {}
        # Shared or scout distances by window: they rank, the plain network answers.
        self.ranking: dict[Corner, float] = {}
        self.strip_maps: StripMaps | None = None  # built on the first shared score
        self.crop_of: dict[Corner, Crop] = {}  # a crop for every window asked for

    @cached_property
    def query_seed(self) -> int:
        """The image's fingerprint, computed when first read: hashing a full-resolution
        image costs 1-7 ms that centre and sweep need not pay."""
        return image_fingerprint(self.image)

    def search_query(self) -> SearchQuery:
        """What an ask/tell search is told of this query."""
        return SearchQuery(self.image.shape[1], self.image.shape[0], lambda: self.query_seed)

    def corners(self, crops: Sequence[Crop]) -> list[Corner]:
        """The strip windows of `crops`, remembering a crop for each.

        Raises:
            DataError: naming query.max_candidates, when the windows the search has
                asked for, these included, are more than it allows.
        """
        corners = [self.strip.window(c) for c in crops]
        asked = len(self.crop_of) + len({c for c in corners if c not in self.crop_of})
        if asked > self.max_candidates:
            height, width = self.image.shape[:2]
            raise DataError(
                f"the crop search asks for {asked} candidate windows of the {width} x "
                f"{height} query image, more than query.max_candidates="
                f"{self.max_candidates} allows (a thin image: lower query.max_aspect; or "
                "a search that tries fewer: crop.stride for crop=sweep, or crop=ga)"
            )
        for corner, crop in zip(corners, crops, strict=True):
            self.crop_of.setdefault(corner, crop)
        return corners

    def unscored(self, corners: Sequence[Corner]) -> list[Corner]:
        """Distinct plain windows among `corners` not scored yet, in order."""
        return list(dict.fromkeys(c for c in corners if c not in self.plain))

    def keep_plain(self, corners: Sequence[Corner], scored: tuple[np.ndarray, NetworkAnswers]):
        distances, answers = scored
        for i, corner in enumerate(corners):
            self.plain[corner] = (float(distances[i]), answers.row(i))

    def score_plain(self, corners: Sequence[Corner]) -> None:
        new = self.unscored(corners)
        if new:
            self.keep_plain(new, self.scorer.plain(self.strip, new))

    def unranked(self, corners: Sequence[Corner]) -> list[Corner]:
        """Distinct windows among `corners` without a shared or scout distance yet."""
        return list(dict.fromkeys(c for c in corners if c not in self.ranking))

    def keep_ranking(self, corners: Sequence[Corner], distances: np.ndarray) -> None:
        self.ranking.update(zip(corners, (float(d) for d in distances), strict=True))

    def score_ranking(self, corners: Sequence[Corner]) -> None:
        """Shared or scout distances of the windows not scored so yet."""
        new = self.unranked(corners)
        if not new:
            return
        if self.scoring == "scout":
            (distances,) = self.scorer.scout_together([(self.strip, new)])
        else:
            if self.strip_maps is None:
                self.strip_maps = self.scorer.strip_maps(self.strip)
            distances = self.scorer.shared(self.strip_maps, new)
        self.keep_ranking(new, distances)

    def distances(self, corners: Sequence[Corner]) -> np.ndarray:
        """[n] distances of windows already scored the way `scoring` says."""
        if self.scoring == "plain":
            return np.array([self.plain[c][0] for c in corners])
        return np.array([self.ranking[c] for c in corners])

    def scores(self, corners: Sequence[Corner]) -> CropScores:
        """Plain windows' distances with their answers (`CropSearch.sees_answers`)."""
        answers = [self.plain[c] for c in corners]
        return CropScores.of(
            np.array([distance for distance, _ in answers]),
            np.stack([a.positions for _, a in answers]),
            np.stack([a.quaternions for _, a in answers]),
            np.stack([a.features for _, a in answers]),
        )

    def __call__(self, crops: Sequence[Crop]) -> np.ndarray:
        corners = self.corners(crops)
        if self.scoring == "plain":
            self.score_plain(corners)
        else:
            self.score_ranking(corners)
        return self.distances(corners)

    def rerank_candidates(self, chosen: Crop, count: int) -> list[Corner]:
        """The windows `rerank` compares: the chosen one first, then the best ranked
        ones (shared or scout distances)."""
        corner = self.strip.window(chosen)
        if count <= 1 or not self.ranking:
            return [corner]
        ranked = sorted(self.ranking, key=self.ranking.__getitem__)
        return list(dict.fromkeys([corner, *ranked]))[:count]

    def rerank(self, chosen: Crop, count: int) -> Crop:
        """With shared or scout scoring, the best of the `count` best windows by those
        distances, by plain distance (the search's own choice always among them);
        `chosen` otherwise.

        The shared or scout distances only rank: the candidates go through the plain
        network in one batch (with other queries' in `localize_many`, scored
        beforehand).
        """
        candidates = self.rerank_candidates(chosen, count)
        if len(candidates) == 1:
            return chosen
        self.score_plain(candidates)
        best = min(candidates, key=lambda c: self.plain[c][0])
        return chosen if best == candidates[0] else self.crop_of[best]

    def answer_of(self, crop: Crop) -> tuple[float, NetworkAnswers]:
        """The plain distance and answer of `crop`'s window (scored here if need be)."""
        corner = self.strip.window(crop)
        self.score_plain([corner])
        return self.plain[corner]

    @property
    def evaluations(self) -> int:
        """Distinct windows scored, plainly, shared or by the scout."""
        return len(set(self.plain) | set(self.ranking))

    def network_passes(self) -> float:
        """Plain windows plus, with shared scoring, the strip pass in window passes,
        and with scout scoring, the scout's passes (each a whole, cheaper one)."""
        strip = 0.0 if self.strip_maps is None else self.scorer.strip_passes(self.strip)
        scouted = len(self.ranking) if self.scoring == "scout" else 0
        return len(self.plain) + strip + scouted
