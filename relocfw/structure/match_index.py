"""The map's descriptors stacked once, for matching queries against any keyframes.

`correspondences_of` on a bare StructureMap concatenates the keyframes' float32
descriptors for every query and matches against every keypoint, also those without
a 3-D point, which can never become a correspondence. A MatchIndex is made once, when
the refiner is fitted or loaded, and holds, for the keypoints that are matched:

- their descriptors as one [T, D] uint8 block on the map's storage grid (a quarter of
  float32's bytes; a keyframe's rows are turned into float32 when a query asks),
- their squared norms (the `||c||^2` of the distance expansion, computed once),
- their 3-D points and each image's rows (`offsets`).

With `points_only` (the default) only keypoints with a 3-D point are kept: on an
RGB-only map most keypoints have none, and matching against them buys nothing but
time. The ratio test's second-nearest is then the second-nearest among those
keypoints of the same keyframe, so a few matches differ from matching against all
keypoints (measured in docs/results/structure.md). `points_only=False` keeps every
keypoint and matches exactly as `correspondences_of` on the map does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from relocfw.core.errors import DataError
from relocfw.structure.features import LocalFeatures
from relocfw.structure.matching import matches_of_distances, one_match_per_query
from relocfw.structure.query_checks import checked_keyframes
from relocfw.structure.structure_map import DESCRIPTOR_SCALE, StructureMap, quantised


@dataclass(frozen=True, eq=False)
class MatchIndex:
    """Matchable keypoints of every map image, stacked (see the module).

    Attributes:
        codes: [T, D] uint8 descriptors (descriptor x 255, the map's storage grid).
        norms: [T] float32 squared norms of the float32 descriptors.
        points: [T, 3] float32 world points (NaN rows only without `points_only`).
        offsets: [M + 1] int64: image i's rows are offsets[i] .. offsets[i + 1].
        points_only: whether keypoints without a 3-D point were left out.
    """

    codes: np.ndarray
    norms: np.ndarray
    points: np.ndarray
    offsets: np.ndarray
    points_only: bool

    @classmethod
    def of(cls, structure: StructureMap, points_only: bool = True) -> MatchIndex:
        """The index of `structure`'s keypoints (with a 3-D point, by default)."""
        if not isinstance(structure, StructureMap):
            raise DataError(f"structure must be a StructureMap, got {type(structure).__name__}")
        dimensions = structure.descriptor_dimensions
        codes, points, counts = [], [], []
        for features, rows in zip(structure.features, structure.points, strict=True):
            kept = np.isfinite(rows).all(axis=1) if points_only else np.ones(len(rows), bool)
            codes.append(quantised(features.descriptors[kept]).reshape(-1, dimensions))
            points.append(rows[kept])
            counts.append(int(kept.sum()))
        stacked = np.concatenate(codes) if codes else np.zeros((0, dimensions), np.uint8)
        offsets = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        descriptors = torch.from_numpy(stacked).to(torch.float32) / DESCRIPTOR_SCALE
        norms = (descriptors * descriptors).sum(dim=1).numpy()
        all_points = np.concatenate(points) if points else np.zeros((0, 3), np.float32)
        for array in (stacked, norms, all_points, offsets):
            array.setflags(write=False)
        return cls(stacked, norms, all_points, offsets, bool(points_only))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def nbytes(self) -> int:
        """Bytes the index holds."""
        return sum(a.nbytes for a in (self.codes, self.norms, self.points, self.offsets))

    def rows_of(self, keyframes: Sequence[int]) -> np.ndarray:
        """The stacked rows of `keyframes`, keyframe after keyframe."""
        spans = [np.arange(self.offsets[k], self.offsets[k + 1]) for k in keyframes]
        return np.concatenate(spans) if spans else np.zeros(0, dtype=np.int64)

    def correspondences(
        self,
        query: LocalFeatures,
        keyframes: Sequence[int],
        ratio: float,
        known: KnownMatches | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The query's 2-D/3-D correspondences through its matches with `keyframes`
        (distinct, in range, best first; query_solver.checked_keyframes).

        One matrix product against all the keyframes' rows, then per keyframe the
        mutual nearest neighbours with the ratio test (matching.matches_of_distances);
        a query keypoint matched in several keyframes keeps its match of the smallest
        distance, a tie going to the earlier keyframe (matching.one_match_per_query).
        A keyframe's matches depend on the query and that keyframe alone, so with
        `known` (the same query's matches from an earlier call) only the keyframes it
        lacks are matched, and they are added to it.

        Returns:
            points_2d [K, 2] float64 query pixels and points_3d [K, 3] float64 world
            points, in query keypoint order; rows whose point is NaN (possible only
            without `points_only`) are dropped.

        Raises:
            DataError: when `known` holds another query's or another ratio's matches.
        """
        keyframes = checked_keyframes(keyframes, len(self))
        if known is None:
            known = KnownMatches()
        known.check(query, ratio)
        if len(query) == 0:
            return np.zeros((0, 2)), np.zeros((0, 3))
        new = [k for k in keyframes if k not in known.by_keyframe]
        rows = self.rows_of(new)
        with torch.inference_mode():
            distances = None
            if len(rows):
                candidates = torch.from_numpy(self.codes[rows]).to(torch.float32)
                candidates /= DESCRIPTOR_SCALE
                query_t = torch.from_numpy(np.array(query.descriptors, dtype=np.float32))
                query_norms = (query_t * query_t).sum(dim=1, keepdim=True)
                candidate_norms = torch.from_numpy(np.array(self.norms[rows]))[None, :]
                distances = torch.addmm(
                    query_norms + candidate_norms, query_t, candidates.T, alpha=-2.0
                ).clamp_(min=0.0)
            start = 0
            for keyframe in new:
                end = start + int(self.offsets[keyframe + 1] - self.offsets[keyframe])
                pairs = (
                    matches_of_distances(distances[:, start:end], ratio)
                    if distances is not None
                    else np.zeros((0, 2), dtype=np.int64)
                )
                # (query keypoint, stacked row of the index) per match.
                known.by_keyframe[keyframe] = np.stack([pairs[:, 0], rows[pairs[:, 1] + start]], 1)
                start = end
        matched = [known.by_keyframe[k] for k in keyframes]
        if not matched or not sum(len(m) for m in matched):
            return np.zeros((0, 2)), np.zeros((0, 3))
        indices = np.concatenate([m[:, 0] for m in matched])
        chosen_rows = np.concatenate([m[:, 1] for m in matched])
        world = self.points[chosen_rows]
        has_point = np.isfinite(world).all(axis=1)
        indices, chosen_rows, world = indices[has_point], chosen_rows[has_point], world[has_point]
        # The distance of each match as matching.match_distances measures it (from the
        # difference, not the expansion), so duplicates resolve as on the bare map.
        difference = query.descriptors[indices] - self.codes[chosen_rows] / np.float32(
            DESCRIPTOR_SCALE
        )
        kept = one_match_per_query(indices, np.einsum("ij,ij->i", difference, difference))
        return (
            query.keypoints[indices[kept]].astype(np.float64),
            world[kept].astype(np.float64),
        )


@dataclass
class KnownMatches:
    """One query's matches per keyframe (MatchIndex.correspondences), kept across the
    solves of that query (a second match near its first answer, a retry after a lost
    track), so a keyframe in both keyframe sets is matched once.

    Attributes:
        by_keyframe: keyframe -> [P, 2] int64 (query keypoint, MatchIndex row) matches.
        query: the query's features they belong to (bound on first use).
        ratio: the ratio test they passed (bound on first use).
    """

    by_keyframe: dict[int, np.ndarray] = field(default_factory=dict)
    query: LocalFeatures | None = None
    ratio: float | None = None

    def check(self, query: LocalFeatures, ratio: float) -> None:
        """Bind to `query` and `ratio` on first use; DataError for another later."""
        if self.query is None:
            self.query, self.ratio = query, ratio
        elif self.query is not query or self.ratio != ratio:
            raise DataError(
                "known matches belong to another query's features or another ratio; "
                "keep one KnownMatches per query"
            )
