"""A crop search that chooses by a test-time selection rule over every window's pose.

crop=rule scores every crop offset (as crop=sweep) and is sent each window's network
answer as well as its map distance (`CropSearch.sees_answers`), then picks the window
that a rule of relocfw.core.window_rules names: `retrieval_consistency` (the window
whose regressed pose agrees best with the poses of its own nearest map images),
`consensus` (the window nearest the robust centre of every window's pose), `gated`
(the paper's window only when the query is far from the map) or `min_distance` /
`centre` (for checks). The rules, and which of them win where, are studied offline on
recorded windows: docs/results/beyond-the-paper.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.interfaces import (
    CropProposals,
    CropScores,
    CropSearch,
    SearchQuery,
    crop_at,
    crop_side_and_span,
)
from relocfw.core.options import integer_at_least
from relocfw.core.standardise import ZScore, k_nearest
from relocfw.core.values import Crop, Pose
from relocfw.core.window_rules import (
    Windows,
    centre,
    consensus,
    gated,
    min_distance,
    retrieval_consistency,
)

# Rules that name a window (a blend of windows is a pose, not a crop).
WINDOW_RULES = ("retrieval_consistency", "consensus", "gated", "min_distance", "centre")
NEEDS_NEIGHBOURS = ("retrieval_consistency",)


class WindowRuleSearch(CropSearch):
    """Every offset scored; the window a selection rule chooses from their answers.

    Args:
        rule: one of WINDOW_RULES.
        neighbours: map images per window for retrieval_consistency (the study's 5).
        threshold: gated's threshold on the query's nearest relative map distance
            (in map-image units), chosen on validation (docs/results/beyond-the-paper.md).
    """

    sees_answers = True
    wants_map = True

    def __init__(
        self, rule: str = "retrieval_consistency", neighbours: int = 5, threshold: float = 1.0
    ) -> None:
        if rule not in WINDOW_RULES:
            raise ConfigError(f"crop.rule must be one of {', '.join(WINDOW_RULES)}, got {rule!r}")
        self.rule = rule
        self.neighbours = integer_at_least("crop.neighbours", neighbours, 1)
        self.threshold = float(threshold)
        if not np.isfinite(self.threshold):
            raise ConfigError(f"crop.threshold must be a finite number, got {threshold!r}")
        self.standardise: ZScore | None = None
        self.map_descriptors: np.ndarray | None = None
        self.map_positions: np.ndarray | None = None
        self.map_quaternions: np.ndarray | None = None
        self.distance_scale: float | None = None

    def fit_map(
        self, descriptors: np.ndarray, poses: Sequence[Pose], distance_scale: float
    ) -> None:
        self.standardise = ZScore().fit(descriptors)
        self.map_descriptors = self.standardise(descriptors)
        self.map_positions = np.array([p.position for p in poses], dtype=np.float64)
        self.map_quaternions = np.array([p.quaternion for p in poses], dtype=np.float64)
        self.distance_scale = float(distance_scale)

    def state(self) -> dict[str, torch.Tensor]:
        """The fitted map, for model files."""
        if self.standardise is None:
            raise DataError("crop=rule has no map yet: Relocalizer.fit first")
        return {
            **{f"standardise.{k}": v for k, v in self.standardise.state().items()},
            "map_descriptors": torch.from_numpy(self.map_descriptors),
            "map_positions": torch.from_numpy(self.map_positions),
            "map_quaternions": torch.from_numpy(self.map_quaternions),
            "distance_scale": torch.tensor(self.distance_scale, dtype=torch.float64),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        prefix = "standardise."
        self.standardise = ZScore().load_state(
            {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        )
        self.map_descriptors = state["map_descriptors"].double().numpy()
        self.map_positions = state["map_positions"].double().numpy()
        self.map_quaternions = state["map_quaternions"].double().numpy()
        self.distance_scale = float(state["distance_scale"])

    def windows(
        self, crops: Sequence[Crop], scores: CropScores, centre_offset: int
    ) -> tuple[Windows, np.ndarray]:
        """The distinct windows of the scored offsets (offsets sharing a window carry
        the same answer; each is counted once, as in the study), and the offset of each."""
        if self.map_positions is None or self.standardise is None:
            raise DataError("crop=rule has no map yet: Relocalizer.fit first")
        answers = np.column_stack([np.asarray(scores), scores.positions, scores.quaternions])
        _, first = np.unique(answers, axis=0, return_index=True)
        keep = np.sort(first)
        starts = np.array([c.x + c.y for c in crops], dtype=np.float64)[keep]
        spread = starts.max() - starts.min()
        offsets = (starts - starts.min()) / spread if spread > 0 else np.full(len(keep), 0.5)
        centre_entry = int(np.argmin(np.abs(answers[keep] - answers[centre_offset]).sum(axis=1)))
        near_positions = near_quaternions = None
        if self.rule in NEEDS_NEIGHBOURS:
            near = k_nearest(
                self.standardise(scores.features[keep]), self.map_descriptors, self.neighbours
            )[1]
            near_positions = self.map_positions[near]
            near_quaternions = self.map_quaternions[near]
        return Windows(
            distances=np.asarray(scores, dtype=np.float64)[keep],
            positions=scores.positions[keep],
            quaternions=scores.quaternions[keep],
            offsets=offsets,
            centre=centre_entry,
            distance_scale=self.distance_scale,
            neighbour_positions=near_positions,
            neighbour_quaternions=near_quaternions,
        ), keep

    def choose(self, windows: Windows) -> int:
        """The entry of the window the rule names."""
        rules = {
            "retrieval_consistency": retrieval_consistency,
            "consensus": consensus,
            "gated": lambda w: gated(w, self.threshold),
            "min_distance": min_distance,
            "centre": centre,
        }
        return int(rules[self.rule](windows).window)

    def propose(self, query: SearchQuery) -> CropProposals:
        _, span = crop_side_and_span(query.width, query.height)
        crops = [crop_at(offset, query.width, query.height) for offset in range(span + 1)]
        scores = yield crops  # every offset in one batch, with each one's answer
        windows, keep = self.windows(crops, scores, span // 2)  # centre: crop_at(span // 2)
        return crops[int(keep[self.choose(windows)])]
