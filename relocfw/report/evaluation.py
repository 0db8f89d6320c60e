"""Running a method over a test split and measuring its errors."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from relocfw.core.errors import ConfigError
from relocfw.core.geometry import QUATERNION_MINIMUM, orientation_error_deg, position_error
from relocfw.core.interfaces import Backbone
from relocfw.core.pipeline import Relocalizer
from relocfw.core.progress import Progress
from relocfw.core.sampling import configured_samples
from relocfw.core.trust_signal import CONFIDENCE
from relocfw.core.values import Crop, Localization, Pose
from relocfw.data.frames import Frame
from relocfw.report.metrics import accuracy_metrics, failed_as_infinite
from relocfw.report.uncertainty import confidence_uncertainty, uncertainty_quality
from relocfw.report.units import METRES, PositionUnit, relabel_key


@dataclass(frozen=True)
class MethodResult:
    """One method's answers on a split, aligned with its frames.

    Errors of a query answered without a finite pose are +inf (relocfw.report.metrics).
    `spread_source` says what a sampled answer's spread comes from ("MC dropout",
    "crop samples", "crop samples + MC dropout"), so tables can name the signal; ""
    when not known (a result built by hand) or not sampled.
    """

    method: str
    frames: tuple[Frame, ...]
    answers: tuple[Localization, ...]
    spread_source: str = field(default="", kw_only=True)

    def failed(self) -> np.ndarray:
        """[N] True where the answer has no usable pose: any non-finite number, or a
        quaternion of (near) zero norm. Both of its errors are then +inf."""
        positions = np.stack([a.pose.position for a in self.answers])
        quaternions = np.stack([a.pose.quaternion for a in self.answers])
        finite = np.isfinite(positions).all(axis=1) & np.isfinite(quaternions).all(axis=1)
        norms = np.linalg.norm(np.where(np.isfinite(quaternions), quaternions, 0.0), axis=1)
        return ~finite | (norms < QUATERNION_MINIMUM)

    def position_errors(self) -> np.ndarray:
        errors = position_error(
            np.stack([a.pose.position for a in self.answers]),
            np.stack([f.pose.position for f in self.frames]),
        )
        return np.where(self.failed(), np.inf, failed_as_infinite(errors))

    def orientation_errors(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            errors = orientation_error_deg(
                np.stack([a.pose.quaternion for a in self.answers]),
                np.stack([f.pose.quaternion for f in self.frames]),
            )
        return np.where(self.failed(), np.inf, failed_as_infinite(errors))


def evaluate(
    method: str,
    relocalizer: Relocalizer,
    frames: Sequence[Frame],
    images: Sequence[np.ndarray],
    quiet: bool = False,
    warm_up: bool = True,
) -> MethodResult:
    """Localize every image with `relocalizer`.

    With `warm_up`, the first image is localized once, untimed and discarded, before
    the timed run: the first query pays for lazy allocations, thread pools and kernel
    choices, and timing it would charge whichever method runs first.
    """
    # A refiner solves each query with its own camera (a test split may come from
    # another sensor than the map) and may read the recording from the frame's name
    # (refine=sequence); other pipelines take images only.
    refined = getattr(relocalizer, "refiner", None) is not None
    cameras = [getattr(frame, "camera", None) for frame in frames]
    names = [getattr(frame, "name", None) for frame in frames]
    if warm_up and len(images):
        if refined:
            relocalizer.localize(images[0], cameras[0], names[0])
            relocalizer.refiner.reset()  # the timed pass starts with no history
        else:
            relocalizer.localize(images[0])
    progress = Progress(len(frames), f"relocalizing ({method})", quiet=quiet)
    answers = []
    # Any object with `localize` works; a Relocalizer's options say how many at once.
    options = getattr(relocalizer, "options", None)
    group = getattr(options, "queries_at_once", 1)
    for start in range(0, len(images), group):
        # Groups of queries share forward passes (Relocalizer.localize_many); one
        # query at a time when queries_at_once is 1, its latency then its own.
        if group == 1 and refined:
            answers.append(relocalizer.localize(images[start], cameras[start], names[start]))
        elif group == 1:
            answers.append(relocalizer.localize(images[start]))
        elif refined:
            chunk = slice(start, start + group)
            answers += relocalizer.localize_many(images[chunk], group, cameras[chunk], names[chunk])
        else:
            answers += relocalizer.localize_many(images[start : start + group], group)
        progress.advance(min(group, len(images) - start))
    progress.close()
    return MethodResult(
        method, tuple(frames), tuple(answers), spread_source=spread_source(relocalizer)
    )


def evaluate_round_robin(
    relocalizers: Mapping[str, Relocalizer],
    frames: Sequence[Frame],
    images: Sequence[np.ndarray],
    quiet: bool = False,
) -> dict[str, MethodResult]:
    """Localize every image with every relocalizer, one query at a time, the methods
    taking turns: query i runs the methods in the order rotated by i.

    Timing methods one after another charges each the machine's moods while it runs
    (another job, a warm or cold cache, the CPU's clock); taking turns query by query
    spreads them over all methods alike, so their times compare. Each method is warmed
    up first, as `evaluate` does, and sees the queries in order (a tracking refiner's
    streams stay whole). Answers are those of `evaluate` with one query at a time.

    Raises:
        ConfigError: a relocalizer answers queries in groups (query.queries_at_once
            > 1), whose time is shared among a group and cannot take turns per query.
    """
    names = list(relocalizers)
    for name in names:
        options = getattr(relocalizers[name], "options", None)
        if getattr(options, "queries_at_once", 1) != 1:
            raise ConfigError(
                f"compare.round_robin times one query at a time, but {name!r} answers "
                f"{options.queries_at_once} at once (query.queries_at_once): set it to 1 "
                "or compare.round_robin=false"
            )
    cameras = [getattr(frame, "camera", None) for frame in frames]
    frame_names = [getattr(frame, "name", None) for frame in frames]

    def localize(relocalizer: Relocalizer, index: int) -> Localization:
        if getattr(relocalizer, "refiner", None) is not None:
            return relocalizer.localize(images[index], cameras[index], frame_names[index])
        return relocalizer.localize(images[index])

    if len(images):
        for relocalizer in relocalizers.values():
            localize(relocalizer, 0)
            if getattr(relocalizer, "refiner", None) is not None:
                relocalizer.refiner.reset()  # the timed pass starts with no history
    answers: dict[str, list[Localization]] = {name: [] for name in names}
    progress = Progress(len(frames), f"relocalizing ({len(names)} methods in turn)", quiet=quiet)
    for index in range(len(images)):
        turn = index % len(names) if names else 0
        for name in names[turn:] + names[:turn]:
            answers[name].append(localize(relocalizers[name], index))
        progress.advance()
    progress.close()
    return {
        name: MethodResult(
            name,
            tuple(frames),
            tuple(answers[name]),
            spread_source=spread_source(relocalizers[name]),
        )
        for name in names
    }


def spread_source(relocalizer: object) -> str:
    """What the chosen crop's samples are, as the uncertainty tables name it; "" when
    nothing is sampled or `relocalizer` is not a Relocalizer (any object with
    `localize` may be evaluated, so every attribute is optional here)."""
    crops = int(getattr(getattr(relocalizer, "options", None), "crop_samples", 0) or 0)
    backbone = getattr(relocalizer, "backbone", None)
    dropout = configured_samples(backbone) if isinstance(backbone, Backbone) else 0
    if crops > 0 and dropout > 0:
        return "crop samples + MC dropout"
    if crops > 0:
        return "crop samples"
    return "MC dropout" if dropout > 0 else ""


def constant_answer(method: str, pose: Pose, frames: Sequence[Frame]) -> MethodResult:
    """Every query answered with the same pose: the floor any method must beat."""
    answer = Localization(pose, Crop(0, 0, 0), float("nan"), 0, 0.0)
    return MethodResult(method, tuple(frames), tuple(answer for _ in frames))


def summarise(result: MethodResult) -> dict[str, float | int | str]:
    """The field's accuracy metrics (relocfw.report.metrics.accuracy_metrics) and costs.

    Keys name metres; a writer renames them for a non-metric dataset
    (relocfw.report.units.relabel_row).

    Time is reported as the median (robust to a slow moment of the machine) and the
    mean over the queries of the timed (warmed-up) run. A failed query counts as
    infinitely wrong. A sampled method (MC dropout, crop samples) or a refined one
    also gets its uncertainty measures (`uncertainty_columns`).
    """
    positions = result.position_errors()
    summary = {
        "method": result.method,
        "queries": len(positions),
        **accuracy_metrics(positions, result.orientation_errors()),
        "median_seconds_per_query": float(np.median([a.seconds for a in result.answers])),
        "mean_seconds_per_query": float(np.mean([a.seconds for a in result.answers])),
        "median_ms_network": 1000.0
        * float(np.median([network_seconds(a) for a in result.answers])),
        "mean_network_passes": float(np.mean([a.network_passes for a in result.answers])),
        "mean_crops_scored": float(np.mean([a.evaluations for a in result.answers])),
    }
    return summary | refine_columns(result) | uncertainty_columns(result) | bound_columns(result)


def network_seconds(answer: Localization) -> float:
    """The part of a query's time before its refiner: the crop search with its network
    passes (the whole time for a method without a refiner). Per query, it and the
    refiner's parts add up to the query's time (their medians, the summary's columns,
    need not add up). With queries_at_once > 1 a query's time is its group's share,
    so this part is only meaningful one query at a time."""
    # "tracking_retry" and "rematch" are a second solve's whole time, whose parts are
    # already added into the others (plugins/features_refiner.py): counted once.
    parts = (
        spent
        for part, spent in answer.refine_seconds.items()
        if part not in ("tracking_retry", "rematch")
    )
    return float(answer.seconds - sum(parts))


def refined_answers(result: MethodResult) -> list[Localization]:
    """The answers a refiner gave: those with a confidence, a fallback or a refiner's
    time (an answer without a refiner has none of them)."""
    return [
        a
        for a in result.answers
        if a.fell_back or np.isfinite(a.refine_confidence) or a.refine_seconds
    ]


def refine_columns(result: MethodResult) -> dict[str, float | int]:
    """A refined method's fallbacks (queries answered with the network's pose because
    the refiner found none), its median confidence and its median ms per part; none
    for a method without a refiner."""
    answers = result.answers
    refined = refined_answers(result)
    if not refined:
        return {}
    columns: dict[str, float | int] = {
        "refine_fell_back": sum(a.fell_back for a in answers),
        "refine_median_confidence": float(np.median([a.refine_confidence for a in refined])),
    }
    parts = dict.fromkeys(part for a in refined for part in a.refine_seconds)
    for part in parts:
        seconds = [a.refine_seconds.get(part, 0.0) for a in refined]
        columns[f"refine_median_ms_{part}"] = 1000.0 * float(np.median(seconds))
    return columns


def bound_columns(result: MethodResult) -> dict[str, float]:
    """How often the answers' bounds held (error at most the bound) and their medians;
    none when the answers carry no bounds (NaN). An infinite bound holds."""
    position_bounds = np.array([a.position_bound for a in result.answers], dtype=np.float64)
    orientation_bounds = np.array(
        [a.orientation_bound_deg for a in result.answers], dtype=np.float64
    )
    if not len(position_bounds) or np.isnan(position_bounds).all():
        return {}
    position_held = result.position_errors() <= position_bounds
    orientation_held = result.orientation_errors() <= orientation_bounds
    return {
        "position_bound_coverage": float(np.mean(position_held)),
        "orientation_bound_coverage": float(np.mean(orientation_held)),
        "both_bounds_coverage": float(np.mean(position_held & orientation_held)),
        "median_position_bound_m": float(np.median(position_bounds)),
        "median_orientation_bound_deg": float(np.median(orientation_bounds)),
        # An infinite bound (too little evidence) holds by definition: how many there
        # were says how much of the coverage is that.
        "infinite_position_bounds": int(np.sum(~np.isfinite(position_bounds))),
        "infinite_orientation_bounds": int(np.sum(~np.isfinite(orientation_bounds))),
    }


CONFIDENCE_SIGNAL = CONFIDENCE  # relocfw.core.trust_signal's name of the refiner's signal


@dataclass(frozen=True)
class UncertaintySignal:
    """What ranks one method's answers from the least to the most trustworthy.

    Attributes:
        name: what the tables' "uncertainty signal" column says: "spread (MC
            dropout)", "spread (crop samples)", ... or CONFIDENCE_SIGNAL.
        position: [N] the uncertainty that ranks position errors (larger: less
            trusted; NaN: none measured, the most uncertain).
        orientation: [N] the one that ranks orientation errors.
        from_confidence: True when both come from the refiner's confidence.
        fell_back: [N] where the refiner fell back to the network's pose.
    """

    name: str
    position: np.ndarray
    orientation: np.ndarray
    from_confidence: bool = False
    fell_back: np.ndarray | None = None


def uncertainty_signal_of(result: MethodResult) -> UncertaintySignal | None:
    """The refiner's confidence of a refined method, else the spreads of a sampled one;
    None when it has neither.

    A method both refined and sampled is measured by its confidence: the refiner
    replaced the network's pose on every accepted query, and the spread measured the
    samples of that network pose, not of the pose answered. The confidence ranks both
    kinds of error (`confidence_uncertainty`: fallbacks the most uncertain).
    """
    if refined_answers(result):
        confidence = np.array([a.refine_confidence for a in result.answers], dtype=np.float64)
        fell_back = np.array([a.fell_back for a in result.answers], dtype=bool)
        uncertainty = confidence_uncertainty(confidence, fell_back)
        if np.all(np.isnan(uncertainty)):
            return None  # every query fell back without a count: nothing ranks them
        return UncertaintySignal(CONFIDENCE_SIGNAL, uncertainty, uncertainty, True, fell_back)
    position = np.array([a.position_spread for a in result.answers], dtype=np.float64)
    if np.all(np.isnan(position)):
        return None
    orientation = np.array([a.orientation_spread_deg for a in result.answers], dtype=np.float64)
    name = f"spread ({result.spread_source})" if result.spread_source else "spread"
    return UncertaintySignal(name, position, orientation)


def uncertainty_of(
    result: MethodResult,
) -> tuple[UncertaintySignal, dict[str, object]] | None:
    """The method's uncertainty signal and relocfw.report.uncertainty's measures of it;
    None when it has none (neither sampled nor refined)."""
    signal = uncertainty_signal_of(result)
    if signal is None:
        return None
    quality = uncertainty_quality(
        result.position_errors(), result.orientation_errors(), signal.position, signal.orientation
    )
    return None if quality is None else (signal, quality)


def uncertainty_quality_of(result: MethodResult) -> dict[str, object] | None:
    """relocfw.report.uncertainty's measures of a method's uncertainty (a sampled
    method's spreads, a refined method's confidence: `uncertainty_signal_of`); None
    when it has none."""
    measured = uncertainty_of(result)
    return None if measured is None else measured[1]


def uncertainty_columns(result: MethodResult) -> dict[str, float | str]:
    """Flat summary columns of the uncertainty measures (none without a signal).

    `uncertainty_signal` names what ranks the queries; `*_uncertainty_error_spearman`
    is the Spearman correlation of that uncertainty with the error (positive for a
    useful signal, whichever it is). A spread-ranked method also keeps the same value
    as `*_spread_error_spearman`, the column earlier summaries had.
    """
    measured = uncertainty_of(result)
    if measured is None:
        return {}
    signal, quality = measured
    columns: dict[str, float | str] = {"uncertainty_signal": signal.name}
    for kind, unit in (("position", "m"), ("orientation", "deg")):
        measures = quality[kind]
        if not signal.from_confidence:
            columns[f"{kind}_spread_error_spearman"] = measures["spearman_spread_error"]
        columns[f"{kind}_uncertainty_error_spearman"] = measures["spearman_uncertainty_error"]
        columns[f"{kind}_ause_{unit}"] = measures["ause"]
        for share, median in measures["median_after_rejecting"].items():
            columns[f"median_{kind}_{unit}_rejecting_{share}"] = median
    return columns


ANSWER_COLUMNS = (
    "crop_x",
    "crop_y",
    "crop_size",
    "distance",
    "crops_scored",
    "network_passes",
    "seconds",
    "position_spread_m",
    "orientation_spread_deg",
    # The refiner's: what its uncertainty measures rank by (NaN / 0 without one).
    "refine_confidence",
    "fell_back",
    # Calibrated error bounds (calibrate.share): NaN where the model has none.
    "position_bound_m",
    "orientation_bound_deg",
)
POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
CSV_COLUMNS = (
    "method",
    "frame",
    *(f"true_{c}" for c in POSE_COLUMNS),
    *(f"est_{c}" for c in POSE_COLUMNS),
    "position_error_m",
    "orientation_error_deg",
    *ANSWER_COLUMNS,
)


def answer_cells(answer: Localization) -> list[str | int]:
    """How the answer was found, in ANSWER_COLUMNS order: crop, similarity, cost, spread,
    the refiner's confidence and fallback."""
    return [
        answer.crop.x,
        answer.crop.y,
        answer.crop.size,
        f"{answer.distance:.6f}",
        answer.evaluations,
        f"{answer.network_passes:.3f}",
        f"{answer.seconds:.6f}",
        f"{answer.position_spread:.6f}",
        f"{answer.orientation_spread_deg:.4f}",
        f"{answer.refine_confidence:.6g}",
        int(answer.fell_back),
        f"{answer.position_bound:.6g}",
        f"{answer.orientation_bound_deg:.6g}",
    ]


def per_image_csv(results: Sequence[MethodResult], unit: PositionUnit = METRES) -> str:
    """One row per method and query image, everything needed to redo the statistics.

    The positions' unit is in the column names (`position_error_m`, or
    `position_error_units` for a non-metric dataset), so the file needs no note.
    """
    stream = io.StringIO()
    writer = csv.writer(stream)
    # Per-query columns carry no metre band, so relabelling never drops one.
    writer.writerow([relabel_key(column, unit) for column in CSV_COLUMNS])
    for result in results:
        rows = zip(
            result.frames,
            result.answers,
            result.position_errors(),
            result.orientation_errors(),
            strict=True,
        )
        for frame, answer, pos_err, ori_err in rows:
            writer.writerow(
                [result.method, frame.name]
                + [f"{v:.6f}" for v in (*frame.pose.position, *frame.pose.quaternion)]
                + [f"{v:.6f}" for v in (*answer.pose.position, *answer.pose.quaternion)]
                + [f"{pos_err:.6f}", f"{ori_err:.4f}"]
                + answer_cells(answer)
            )
    return stream.getvalue()
