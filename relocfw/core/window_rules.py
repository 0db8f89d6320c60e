"""Test-time selection rules: which pose to answer, given every window of a query.

A query's square windows (the crop offsets crop=sweep tries) each have a map distance
and a regressed pose. The paper answers with the window nearest the map; the centre
crop answers with the middle one. A rule here is any function of what is known at
query time (distances, poses, where each window sits, the poses of each window's
nearest map images) that returns a pose. The rules are pure numpy, so the study of
recorded windows (relocfw.report.rule_study) and the query-time plugin
(plugins/window_rule_crop.py, `crop=rule`) run the very same code.

Distances are compared across models through `distance_scale` (the map images' own
median map distance), so a threshold or temperature chosen on a validation model
means the same on a test model.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from relocfw.core.geometry import mean_quaternion, orientation_error_deg, rows_on_one_hemisphere

WEISZFELD_STEPS = 50
WEISZFELD_FLOOR = 1e-9  # a distance below this counts as sitting on the median
FAILED_ERROR = 1e3  # metres: what a failed window counts as when a selector learns


@dataclass(frozen=True)
class Windows:
    """One query's distinct windows (offsets that share a window appear once).

    Attributes:
        distances: [n] map distance of each window's descriptor.
        positions: [n, 3] each window's regressed position.
        quaternions: [n, 4] each window's regressed orientation (w, x, y, z).
        offsets: [n] where each window sits along the image's long axis, 0 at one
            end and 1 at the other (the centre window near 0.5).
        centre: the entry of the centre crop.
        distance_scale: the map images' median map distance (for the same model and
            map): distances / distance_scale are comparable across models.
        neighbour_positions: [n, K, 3] positions of each window's K nearest map
            images (by descriptor), or None when they were not recorded.
        neighbour_quaternions: [n, K, 4], or None.
    """

    distances: np.ndarray
    positions: np.ndarray
    quaternions: np.ndarray
    offsets: np.ndarray
    centre: int
    distance_scale: float = 1.0
    neighbour_positions: np.ndarray | None = None
    neighbour_quaternions: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.distances)
        if n == 0:
            raise ValueError("a query needs at least one window")
        shapes = {
            "positions": (self.positions.shape, (n, 3)),
            "quaternions": (self.quaternions.shape, (n, 4)),
            "offsets": (self.offsets.shape, (n,)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"Windows.{name} has shape {got}, expected {want}")
        if not 0 <= self.centre < n:
            raise ValueError(f"Windows.centre {self.centre} is not one of the {n} windows")
        if not self.distance_scale > 0:
            raise ValueError(f"Windows.distance_scale must be > 0, got {self.distance_scale}")

    @property
    def count(self) -> int:
        return len(self.distances)

    @property
    def relative_distances(self) -> np.ndarray:
        """Distances in units of the map images' own median distance."""
        return np.asarray(self.distances, dtype=np.float64) / self.distance_scale


@dataclass(frozen=True)
class Choice:
    """A rule's answer: a pose, and the window it is (None for a blend of windows)."""

    position: np.ndarray
    quaternion: np.ndarray
    window: int | None = None


def along_axis(starts: np.ndarray) -> np.ndarray:
    """Windows' `offsets` from where each starts along the long axis: 0 at one end,
    1 at the other, 0.5 for all when they do not move."""
    starts = np.asarray(starts, dtype=np.float64)
    spread = starts.max() - starts.min()
    return (starts - starts.min()) / spread if spread > 0 else np.full(len(starts), 0.5)


def window_choice(windows: Windows, i: int) -> Choice:
    return Choice(windows.positions[i], rows_on_one_hemisphere(windows.quaternions[i]), int(i))


def geometric_median(points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The point minimising the (weighted) sum of Euclidean distances (Weiszfeld).

    Robust to outliers in a way the mean is not: up to half the points can move
    anywhere and the median stays among the others.
    """
    points = np.asarray(points, dtype=np.float64)
    weights = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    estimate = np.average(points, axis=0, weights=weights)
    for _ in range(WEISZFELD_STEPS):
        gaps = np.linalg.norm(points - estimate, axis=1)
        on = gaps < WEISZFELD_FLOOR
        if not on.any():
            pull = weights / gaps
            moved = pull @ points / pull.sum()
        else:  # sitting on a point (Vardi & Zhang): it is the median unless the others
            away = ~on  # pull harder than its own weight holds
            if not away.any():
                return estimate
            pull = weights[away] / gaps[away]
            held = weights[on].sum()
            strength = np.linalg.norm(pull @ (points[away] - estimate))
            if strength <= held:
                return estimate
            step = held / strength
            moved = (1 - step) * (pull @ points[away] / pull.sum()) + step * estimate
        if np.linalg.norm(moved - estimate) < 1e-12:
            return moved
        estimate = moved
    return estimate


def rotation_median(quaternions: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """A robust average rotation: the chordal mean, reweighted by 1 / angle to it
    (Weiszfeld on the rotation angle), so a few flipped windows barely move it."""
    weights = (
        np.ones(len(quaternions)) if weights is None else np.asarray(weights, dtype=np.float64)
    )
    estimate = mean_quaternion(quaternions, weights)
    for _ in range(WEISZFELD_STEPS // 5):
        angles = np.maximum(orientation_error_deg(quaternions, estimate[None]), 1e-6)
        estimate = mean_quaternion(quaternions, weights / angles)
    return estimate


def deviations(windows: Windows, position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """[n] each window's pose distance from a pose: position and orientation gaps, each
    in units of its median over the windows, added (scale-free: metres and degrees
    need no exchange rate)."""
    gaps = np.linalg.norm(windows.positions - position, axis=1)
    angles = orientation_error_deg(windows.quaternions, quaternion[None])
    return gaps / max(np.median(gaps), 1e-12) + angles / max(np.median(angles), 1e-12)


# --- the rules ---------------------------------------------------------------------


def centre(windows: Windows) -> Choice:
    """PoseNet: the centre crop's pose."""
    return window_choice(windows, windows.centre)


def min_distance(windows: Windows) -> Choice:
    """The paper: the window nearest the map (first on ties, as crop=sweep)."""
    return window_choice(windows, int(np.argmin(windows.distances)))


def soft_min_distance(windows: Windows, tau: float) -> Choice:
    """Every window's pose weighted by exp(-(d - d_min) / tau), d in map-image units.

    tau -> 0 is min_distance; tau = inf is the plain mean of every window (test-time
    augmentation over crops).
    """
    relative = windows.relative_distances
    if np.isinf(tau):
        weights = np.ones(windows.count)
    else:
        weights = np.exp(-(relative - relative.min()) / tau)
    position = np.average(windows.positions, axis=0, weights=weights)
    return Choice(position, mean_quaternion(windows.quaternions, weights))


def robust_mean(windows: Windows) -> Choice:
    """The windows' geometric-median position and median rotation (robust TTA)."""
    return Choice(geometric_median(windows.positions), rotation_median(windows.quaternions))


def consensus(windows: Windows) -> Choice:
    """The window whose pose is nearest the robust centre of every window's pose."""
    centre_pose = robust_mean(windows)
    gaps = deviations(windows, centre_pose.position, centre_pose.quaternion)
    return window_choice(windows, int(np.argmin(gaps)))


def neighbour_disagreement(windows: Windows) -> np.ndarray:
    """[n] how far each window's pose is from the robust centre of the poses of its
    own nearest map images (scale-free, as `deviations`)."""
    if windows.neighbour_positions is None or windows.neighbour_quaternions is None:
        raise ValueError(
            "this rule needs each window's nearest map images: run task=diagnose, "
            "which records them"
        )
    gaps = np.empty(windows.count)
    angles = np.empty(windows.count)
    for i in range(windows.count):
        where = geometric_median(windows.neighbour_positions[i])
        facing = rotation_median(windows.neighbour_quaternions[i])
        gaps[i] = np.linalg.norm(windows.positions[i] - where)
        angles[i] = orientation_error_deg(windows.quaternions[i], facing)
    return gaps / max(np.median(gaps), 1e-12) + angles / max(np.median(angles), 1e-12)


def retrieval_consistency(windows: Windows) -> Choice:
    """The window whose regressed pose agrees best with its nearest map images'."""
    return window_choice(windows, int(np.argmin(neighbour_disagreement(windows))))


def gated(windows: Windows, threshold: float) -> Choice:
    """The paper's window when the query is far from the map (its nearest window's
    relative distance above `threshold`), else the centre crop."""
    if windows.relative_distances.min() > threshold:
        return min_distance(windows)
    return centre(windows)


def window_features(windows: Windows) -> np.ndarray:
    """[n, F] what a learned selector may know of each window at query time; every
    column is scale-free (map-image units, ranks, shares), so a model fitted on one
    network's validation windows reads another's test windows alike. FEATURE_NAMES
    names the columns."""
    relative = windows.relative_distances
    centre_pose = robust_mean(windows)
    ranks = np.argsort(np.argsort(relative, kind="stable"), kind="stable")
    columns = [
        relative,
        relative - relative.min(),
        relative - relative[windows.centre],
        ranks / max(windows.count - 1, 1),
        np.abs(windows.offsets - windows.offsets[windows.centre]),
        deviations(windows, centre_pose.position, centre_pose.quaternion),
        np.full(windows.count, relative.min()),
    ]
    if windows.neighbour_positions is not None:
        columns.append(neighbour_disagreement(windows))
    return np.column_stack(columns)


FEATURE_NAMES = (
    "relative_distance",
    "above_nearest",
    "above_centre",
    "distance_rank",
    "off_centre",
    "consensus_deviation",
    "query_nearest",
    "neighbour_disagreement",
)


@dataclass
class LearnedSelector:
    """Predicts each window's position error from `window_features`, answers with
    the window predicted best. Fitted on validation windows only: `fitted_on` keeps
    the frames it saw, so a study can assert no test query was among them.

    The target is the window's error minus its query's centre-crop error, so the
    model learns which windows beat the centre, not which queries are easy.
    """

    seed: int = 0
    fitted_on: tuple[str, ...] = field(default_factory=tuple)
    model: object | None = None

    def fit(
        self, queries: list[Windows], position_errors: list[np.ndarray], frames: list[str]
    ) -> LearnedSelector:
        from sklearn.ensemble import HistGradientBoostingRegressor

        features = np.concatenate([window_features(w) for w in queries])
        # A failed window (inf) is capped: the regressor needs finite targets.
        capped = [np.minimum(e, FAILED_ERROR) for e in position_errors]
        targets = np.concatenate([e - e[w.centre] for w, e in zip(queries, capped, strict=True)])
        self.model = HistGradientBoostingRegressor(
            max_iter=200, learning_rate=0.05, max_leaf_nodes=15, random_state=self.seed
        ).fit(features, targets)
        self.fitted_on = tuple(frames)
        return self

    def __call__(self, windows: Windows) -> Choice:
        if self.model is None:
            raise ValueError("LearnedSelector.fit first, on validation windows")
        predicted = self.model.predict(window_features(windows))
        best = int(np.argmin(predicted))
        # Only leave the centre where the model expects a gain.
        return window_choice(windows, best if predicted[best] < 0 else windows.centre)


Rule = Callable[[Windows], Choice]
# Every rule by its configuration name (crop=rule crop.rule=NAME), in one table that
# the plugin and the study share. Rules that name a window come first, then the blends.
RULE_NAMES = (
    *("centre", "min_distance", "consensus", "retrieval_consistency", "gated"),
    *("mean", "robust_mean", "soft_min_distance"),
)
NEEDS_NEIGHBOURS = ("retrieval_consistency",)  # each window's nearest map images


def rule_named(name: str, tau: float = 1.0, threshold: float = 1.0) -> Rule:
    """The rule called `name` (one of RULE_NAMES), with its setting where it has one.

    Args:
        tau: soft_min_distance's temperature (map-image units; inf is `mean`).
        threshold: gated's threshold on the query's nearest relative map distance.
    """
    rules: Mapping[str, Rule] = {
        "centre": centre,
        "min_distance": min_distance,
        "consensus": consensus,
        "retrieval_consistency": retrieval_consistency,
        "gated": lambda windows: gated(windows, threshold),
        "mean": lambda windows: soft_min_distance(windows, np.inf),
        "robust_mean": robust_mean,
        "soft_min_distance": lambda windows: soft_min_distance(windows, tau),
    }
    if name not in rules:
        raise ValueError(f"unknown rule {name!r}; known: {', '.join(RULE_NAMES)}")
    return rules[name]
