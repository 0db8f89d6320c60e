"""A crop search that answers by a test-time selection rule over every window's pose.

crop=rule scores every crop offset (as crop=sweep) and is sent each window's network
answer as well as its map distance (`CropSearch.sees_answers`), then answers as a rule
of relocfw.core.window_rules says. Rules that name a window: `consensus` (the window
nearest the robust centre of every window's pose), `retrieval_consistency` (the window
whose regressed pose agrees best with the poses of its own nearest map images),
`gated` (the paper's window only when the query is far from the map), `min_distance`
and `centre` (for checks). Rules that blend windows: `mean` (every window's pose
averaged: test-time augmentation over crops), `robust_mean` (geometric-median position,
median rotation) and `soft_min_distance` (weights exp(-excess distance / tau)); their
crop is the window nearest the blended pose, and the blend is the answer
(relocfw.core.values.CropWithPose). Which rules win where is studied offline on
recorded windows: docs/results/beyond-the-paper.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError, RelocfwError
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
from relocfw.core.values import Crop, CropWithPose, Pose
from relocfw.core.window_rules import (
    NEEDS_NEIGHBOURS,
    RULE_NAMES,
    Choice,
    Windows,
    along_axis,
    deviations,
    rule_named,
)


class WindowRuleSearch(CropSearch):
    """Every offset scored; the answer a selection rule gives from their answers.

    Args:
        rule: one of relocfw.core.window_rules.RULE_NAMES.
        neighbours: map images per window for retrieval_consistency (the study's 5).
        threshold: gated's threshold on the query's nearest relative map distance
            (in map-image units), chosen on validation (docs/results/beyond-the-paper.md).
        tau: soft_min_distance's temperature (map-image units).
    """

    sees_answers = True
    wants_map = True

    def __init__(
        self,
        rule: str = "mean",
        neighbours: int = 5,
        threshold: float = 1.0,
        tau: float = 1.0,
    ) -> None:
        if rule not in RULE_NAMES:
            raise ConfigError(f"crop.rule must be one of {', '.join(RULE_NAMES)}, got {rule!r}")
        self.rule = rule
        self.neighbours = integer_at_least("crop.neighbours", neighbours, 1)
        self.threshold = float(threshold)
        if not np.isfinite(self.threshold):
            raise ConfigError(f"crop.threshold must be a finite number, got {threshold!r}")
        self.tau = float(tau)
        if not self.tau > 0:
            raise ConfigError(f"crop.tau must be > 0 (inf: the plain mean), got {tau!r}")
        self.rule_function: Callable[[Windows], Choice] = rule_named(
            rule, tau=self.tau, threshold=self.threshold
        )
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
        if not isinstance(scores, CropScores):
            raise RelocfwError(
                "crop=rule chooses by each crop's network answer, which a plain distance "
                "function does not give: run it through a Relocalizer"
            )
        answers = np.column_stack([np.asarray(scores), scores.positions, scores.quaternions])
        _, first = np.unique(answers, axis=0, return_index=True)
        keep = np.sort(first)
        offsets = along_axis(np.array([c.x + c.y for c in crops])[keep])
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

    def choose(self, windows: Windows) -> Choice:
        """The rule's answer for the query's windows."""
        return self.rule_function(windows)

    def propose(self, query: SearchQuery) -> CropProposals:
        _, span = crop_side_and_span(query.width, query.height)
        crops = [crop_at(offset, query.width, query.height) for offset in range(span + 1)]
        scores = yield crops  # every offset in one batch, with each one's answer
        windows, keep = self.windows(crops, scores, span // 2)  # centre: crop_at(span // 2)
        choice = self.choose(windows)
        if choice.window is not None:
            return crops[int(keep[choice.window])]
        # A blend: reported on the window nearest it, answered with the blended pose.
        nearest = int(np.argmin(deviations(windows, choice.position, choice.quaternion)))
        crop = crops[int(keep[nearest])]
        return CropWithPose(crop.x, crop.y, crop.size, Pose(choice.position, choice.quaternion))
