"""The crop-headroom diagnostic: does the crop closest to the map give a better pose?

The paper's premise is that, of the square crops of a query, the one whose
descriptor lies nearest the map yields the most accurate pose. A crop search can only
be as good as that premise, so this module measures it directly, for any fitted
Relocalizer: every crop offset of every test query is scored once (the windows the
sweep would try, relocfw.report.window_scores), and `summarise_headroom` compares three
choices per query: the centre crop (PoseNet), the crop of smallest map distance (a
perfect search of the paper's objective) and the oracle crop (the best any crop could
do, chosen with the ground truth). No Hydra here: the task that runs it and writes its files
(relocfw.app.tasks.diagnose) sits on top.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from relocfw.core.geometry import orientation_error_deg, position_error
from relocfw.core.pipeline import Relocalizer
from relocfw.core.progress import Progress
from relocfw.core.standardise import ZScore, k_nearest
from relocfw.core.values import Pose
from relocfw.data.frames import Frame
from relocfw.report.statistics import spearman
from relocfw.report.window_scores import score_windows


@dataclass(frozen=True)
class QueryWindows:
    """One query's every crop offset: where it is, how near the map, how wrong its pose.

    Entry i is offset i along the image's long axis; errors are against the query's
    ground truth, with a non-finite pose counted as infinitely wrong (never dropped,
    which would flatter a method that fails).
    """

    frame: str
    crops: np.ndarray  # [n, 3] int: x, y, size in original image pixels
    views: np.ndarray  # [n, 3] float: x, y, side of what the network sees of each crop
    distances: np.ndarray  # [n] map distance of each crop's descriptor
    position_errors: np.ndarray  # [n] metres, inf for a non-finite pose
    orientation_errors: np.ndarray  # [n] degrees, inf for a non-finite pose
    centre: int  # entry of the centre crop, the window crop=centre uses
    windows: int  # distinct network inputs scored (offsets may share a window)
    # What a selection rule may use (relocfw.core.window_rules), and the truth:
    positions: np.ndarray | None = None  # [n, 3] each crop's regressed position
    quaternions: np.ndarray | None = None  # [n, 4] and orientation (w, x, y, z)
    neighbours: np.ndarray | None = None  # [n, K] its nearest map images (by descriptor)
    distance_scale: float = float("nan")  # a unit of map distance (Scorer.distance_scale)
    truth: Pose | None = None

    @property
    def offsets(self) -> np.ndarray:
        return np.arange(len(self.distances))


@dataclass(frozen=True)
class Picks:
    """Entries chosen among one query's offsets by each rule."""

    centre: int
    min_distance: int  # what crop=sweep at stride 1 returns (first on ties, as np.argmin)
    oracle_position: int  # smallest position error; orientation breaks ties
    oracle_orientation: int  # smallest orientation error; position breaks ties


CHOICES = ("centre", "min_distance", "oracle_position", "oracle_orientation")


def pose_errors(
    positions: np.ndarray, quaternions: np.ndarray, truth: Pose
) -> tuple[np.ndarray, np.ndarray]:
    """[n] position (m) and orientation (deg) errors; inf where the pose is not finite."""
    positions = np.asarray(positions, dtype=np.float64)
    quaternions = np.asarray(quaternions, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        position = position_error(positions, truth.position[None])
        orientation = orientation_error_deg(quaternions, truth.quaternion[None])
    broken = ~(np.isfinite(positions).all(axis=1) & np.isfinite(quaternions).all(axis=1))
    position = np.where(broken | ~np.isfinite(position), np.inf, position)
    orientation = np.where(broken | ~np.isfinite(orientation), np.inf, orientation)
    return position, orientation


class MapNeighbours:
    """Each window's nearest map images by descriptor, exactly, whatever the index:
    descriptors standardised as the indexes standardise them (relocfw.core.standardise),
    then Euclidean nearest neighbours."""

    def __init__(self, map_features: np.ndarray, count: int) -> None:
        self.standardise = ZScore().fit(map_features)
        self.points = self.standardise(map_features)
        self.count = count

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return k_nearest(self.standardise(features), self.points, self.count)[1]


def diagnose(
    relocalizer: Relocalizer,
    frames: Sequence[Frame],
    images: Sequence[np.ndarray],
    quiet: bool = True,
    map_features: np.ndarray | None = None,
    neighbours: int = 5,
) -> tuple[QueryWindows, ...]:
    """Every crop offset of every query, scored by a fitted Relocalizer.

    Args:
        relocalizer: with its map already fitted; its crop search is not used.
        frames: the queries' ground truth, aligned with `images`.
        images: RGB uint8 query images.
        quiet: no progress bar.
        map_features: the map images' descriptors (what `Relocalizer.fit` returned):
            with them each window also gets its `neighbours` nearest map images, and
            every query the map's `distance_scale`.
    """
    finder, scale = None, float("nan")
    if map_features is not None:
        finder = MapNeighbours(map_features, neighbours)
        scale = relocalizer.scorer.distance_scale(map_features)
    progress = Progress(len(images), "scoring every crop offset", quiet=quiet)
    queries = []
    for frame, image in zip(frames, images, strict=True):
        scores = score_windows(relocalizer, image)
        position, orientation = pose_errors(scores.positions, scores.quaternions, frame.pose)
        queries.append(
            QueryWindows(
                frame=frame.name,
                crops=np.array([(c.x, c.y, c.size) for c in scores.crops], dtype=np.int64),
                views=scores.views(),
                distances=scores.distances,
                position_errors=position,
                orientation_errors=orientation,
                centre=scores.centre,
                windows=scores.windows,
                positions=scores.positions,
                quaternions=scores.quaternions,
                neighbours=None if finder is None else finder(scores.features),
                distance_scale=scale,
                truth=frame.pose,
            )
        )
        progress.advance()
    progress.close()
    return tuple(queries)


def pick(
    distances: np.ndarray,
    position_errors: np.ndarray,
    orientation_errors: np.ndarray,
    centre: int,
) -> Picks:
    """The entries the centre, min-distance and oracle rules choose for one query."""
    position_errors = np.asarray(position_errors, dtype=np.float64)
    orientation_errors = np.asarray(orientation_errors, dtype=np.float64)
    return Picks(
        centre=int(centre),
        # np.argmin, as SweepCrop: the same window a perfect search returns.
        min_distance=int(np.argmin(distances)),
        oracle_position=int(np.lexsort((orientation_errors, position_errors))[0]),
        oracle_orientation=int(np.lexsort((position_errors, orientation_errors))[0]),
    )


def signed_rank_p(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """Two-sided paired Wilcoxon signed-rank p value of a vs b, and the pairs it used.

    Tied pairs (two infinite errors included) carry no sign and are left out, as
    scipy's default does. The test only ranks |a - b|, so an infinite difference is
    replaced by a finite one larger than every other, keeping its sign and rank.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        differences = a - b
    differences = differences[(a != b) & ~np.isnan(differences)]
    if len(differences) == 0:
        return float("nan"), 0
    infinite = np.isinf(differences)
    if infinite.any():
        finite = np.abs(differences[~infinite])
        largest = 2.0 * (finite.max() if len(finite) else 1.0) + 1.0
        differences = np.where(infinite, np.sign(differences) * largest, differences)
    return float(stats.wilcoxon(differences).pvalue), len(differences)


def error_summary(position: np.ndarray, orientation: np.ndarray) -> dict[str, float]:
    return {
        "median_position_m": float(np.median(position)),
        "mean_position_m": float(np.mean(position)),
        "median_orientation_deg": float(np.median(orientation)),
        "mean_orientation_deg": float(np.mean(orientation)),
    }


def distinct_windows(distances: np.ndarray, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each distinct window once: offsets that round to one window share its distance
    and error, and counting them several times would weight that window in a rank
    correlation by how many offsets land on it."""
    pairs = np.unique(np.column_stack([distances, errors]), axis=0)
    return pairs[:, 0], pairs[:, 1]


def summarise_headroom(
    distances: Sequence[np.ndarray],
    position_errors: Sequence[np.ndarray],
    orientation_errors: Sequence[np.ndarray],
    centres: Sequence[int],
) -> dict[str, Any]:
    """The headroom numbers of one scene from per-query arrays (one entry per offset).

    Pure, so it can be checked on constructed arrays. Returns a JSON-ready dict:
    `errors` (median/mean of each choice of CHOICES), `min_distance_vs_centre` (share
    of queries where min-distance is more / less accurate in position, paired
    Wilcoxon p), `spearman_within` (rank correlation of distance with position error
    over each query's distinct windows: median over queries and share positive) and
    `spearman_across` (each query's min distance vs its window's position error).
    """
    count = len(distances)
    if not count or not (count == len(position_errors) == len(orientation_errors) == len(centres)):
        raise ValueError("summarise_headroom needs one array of each kind per query, >= 1")
    picks = [
        pick(d, p, o, c)
        for d, p, o, c in zip(distances, position_errors, orientation_errors, centres, strict=True)
    ]
    chosen = {
        name: (
            np.array([p[getattr(k, name)] for p, k in zip(position_errors, picks, strict=True)]),
            np.array([o[getattr(k, name)] for o, k in zip(orientation_errors, picks, strict=True)]),
        )
        for name in CHOICES
    }
    searched, centre = chosen["min_distance"][0], chosen["centre"][0]
    p_value, pairs = signed_rank_p(searched, centre)
    within = np.array(
        [spearman(*distinct_windows(d, p)) for d, p in zip(distances, position_errors, strict=True)]
    )
    defined = within[~np.isnan(within)]
    nearest = np.array(
        [np.asarray(d)[k.min_distance] for d, k in zip(distances, picks, strict=True)]
    )
    return {
        "queries": count,
        "mean_offsets_per_query": float(np.mean([len(d) for d in distances])),
        "errors": {name: error_summary(*chosen[name]) for name in CHOICES},
        "min_distance_vs_centre": {
            "share_better_position": float(np.mean(searched < centre)),
            "share_worse_position": float(np.mean(searched > centre)),
            "wilcoxon_p_position": p_value,
            "wilcoxon_pairs": pairs,
        },
        "spearman_within": {
            "median": float(np.median(defined)) if len(defined) else float("nan"),
            "share_positive": float(np.mean(defined > 0)) if len(defined) else float("nan"),
            "queries": int(len(defined)),
        },
        "spearman_across": spearman(nearest, searched),
    }


def summarise_queries(queries: Sequence[QueryWindows]) -> dict[str, Any]:
    """`summarise_headroom` of diagnosed queries."""
    return summarise_headroom(
        [q.distances for q in queries],
        [q.position_errors for q in queries],
        [q.orientation_errors for q in queries],
        [q.centre for q in queries],
    )


def picks_of(queries: Sequence[QueryWindows]) -> list[Picks]:
    return [pick(q.distances, q.position_errors, q.orientation_errors, q.centre) for q in queries]
