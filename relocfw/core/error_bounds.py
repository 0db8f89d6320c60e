"""Calibrated error bounds: split conformal prediction over bins of a trust signal.

A model answers held-out validation queries whose true poses are known; their position
and orientation errors calibrate a bound that a new answer's error stays under with
probability of about `coverage` (e.g. 90%), assuming the new query and the validation
queries are exchangeable (drawn alike). Nothing is assumed about the error's
distribution: the bound is an order statistic of the validation errors. "About":
within a group of fixed membership the finite-sample rank below gives at least
`coverage`; the bins' edges, though, are quantiles of the same validation signals
they sort, so the per-bin guarantee is approximate, off by up to about one answer in
a bin (5 points at the least bin of 20). Queries farther from the map than the
validation block are not exchangeable with it: their coverage is measured, not
promised (relocfw.report.calibration).

The bound adapts to how much an answer can be trusted. A trust signal (the refiner's
confidence, the spread of sampled answers; higher = more trusted) sorts the answers
into groups, and each group gets its own conformal bound (group-conditional, or
"Mondrian", conformal prediction). Then the coverage holds within each group, not
only on average, so a confident answer gets a tight bound and a doubtful one a wide
one. The groups of one calibration:

- bins of the signal: the answers with a finite signal that did not fall back are cut
  into equal-count bins at signal quantiles (`edges`). A signal equal to an edge
  belongs to the bin above it, the more trusted one (np.searchsorted, side="right",
  in both calibration and lookup).
- the untrusted group: answers the caller marks untrusted (relocfw.core.trust_signal:
  fell back, or no finite confidence or spread under those signals), and answers with
  no finite signal while the signal splits the answers into two or more bins.

With one bin the signal ranks nothing, so an answer without a finite signal that the
caller did not mark untrusted joins that one bin. That is what makes signal "none"
work: no answer has a signal (a plain network without a spread), and every answer is
bound by the one marginal bin. Calibration and lookup share this rule (`_groups`), so
a new answer is grouped exactly as a validation answer would have been, which is what
the guarantee needs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError

SIGNALS = ("refiner confidence", "spread", "none")  # what ranks trust; stored as an index

# The most bins a stored state may hold: a forged count must not allocate without end.
MOST_BINS = 1000
# The coverages a bound may be calibrated for (a stored one loads anywhere in (0, 1),
# as older relocfw calibrated there). Below one half a "bound" is exceeded by most
# answers, and a coverage near 0 asks for the 0th smallest error; above 0.999 each
# bin needs over 999 validation answers for a finite bound.
LEAST_COVERAGE = 0.5
MOST_COVERAGE = 0.999
# (n + 1) * coverage is a rational number that binary floats round: 10 * 0.9 may land
# a hair above 9, and its ceiling would then ask for one more answer than the rule does.
ROUNDING = 1e-9
UNTRUSTED = -1  # the group index `_groups` gives the untrusted group


def conformal_rank(count: int, coverage: float) -> int:
    """ceil((count + 1) * coverage): which smallest of `count` errors bounds a new one."""
    return math.ceil((count + 1) * coverage - ROUNDING)


def least_answers(coverage: float) -> int:
    """The fewest answers that give a finite conformal bound at `coverage`:
    count >= coverage / (1 - coverage)."""
    return math.ceil(coverage / (1 - coverage) - ROUNDING)


def answers_per_bin(coverage: float) -> int:
    """The fewest answers a bin is made with: enough for a finite conformal bound
    (`least_answers`), and never fewer than 20."""
    return max(20, least_answers(coverage))


def supports(count: int, coverage: float) -> bool:
    """Whether `count` answers can give a finite bound at `coverage`: its conformal
    rank is one of them."""
    return conformal_rank(count, coverage) <= count


def conformal_bound(errors: np.ndarray, coverage: float) -> float:
    """The conformal_rank-th smallest of `errors`; +inf when that rank exceeds their
    number (too few answers to bound at this coverage, which is honest, not a guess)."""
    rank = conformal_rank(len(errors), checked_coverage(coverage, "coverage", ConfigError))
    if rank > len(errors):
        return math.inf
    return float(np.partition(errors, rank - 1)[rank - 1])


def _groups(edges: np.ndarray, signal: np.ndarray, untrusted: np.ndarray) -> np.ndarray:
    """Each answer's group: its bin (0 = least trusted) or UNTRUSTED. The module's note
    gives the rule; calibration and lookup both use this one function."""
    finite = np.isfinite(signal)
    if len(edges) == 0:
        bins = np.zeros(len(signal), dtype=np.int64)
        return np.where(untrusted, UNTRUSTED, bins)
    # Ties go to the more trusted bin: searchsorted's "right" counts the edges <= signal.
    bins = np.searchsorted(edges, np.where(finite, signal, 0.0), side="right").astype(np.int64)
    return np.where(untrusted | ~finite, UNTRUSTED, bins)


@dataclass(frozen=True)
class BinnedBound:
    """Split-conformal bound of one error (position in the map's units, or orientation deg)
    per bin of a trust signal (higher signal = more trusted)."""

    edges: np.ndarray  # [B-1] ascending finite signal values between bins
    bounds: np.ndarray  # [B] bound per bin, least trusted (bin 0) first; non-increasing; may be inf
    counts: np.ndarray  # [B] int64 validation answers per bin
    untrusted_bound: float  # bound for answers without a signal value or that fell back
    untrusted_count: int

    def __post_init__(self) -> None:
        # Read-only copies, so a caller's later edits cannot change a frozen bound.
        for name, dtype in (("edges", np.float64), ("bounds", np.float64), ("counts", np.int64)):
            array = np.array(getattr(self, name), dtype=dtype).reshape(-1)
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        object.__setattr__(self, "untrusted_bound", float(self.untrusted_bound))
        object.__setattr__(self, "untrusted_count", int(self.untrusted_count))

    def bound(self, signal: float, untrusted: bool) -> float:
        """The bound of one answer's error, from its trust signal (NaN: none) and
        whether it fell back."""
        return float(self.bounds_of(np.array([signal]), np.array([untrusted]))[0])

    def bounds_of(self, signal: np.ndarray, untrusted: np.ndarray) -> np.ndarray:
        """`bound` of each of N answers: [N] signals (NaN: none), [N] fell-back flags."""
        signal = np.asarray(signal, dtype=np.float64).reshape(-1)
        untrusted = np.asarray(untrusted, dtype=bool).reshape(-1)
        if len(signal) != len(untrusted):
            raise DataError(
                f"error bounds: {len(signal)} signals but {len(untrusted)} fell-back flags"
            )
        groups = _groups(self.edges, signal, untrusted)
        binned = self.bounds[np.maximum(groups, 0)]
        return np.where(groups == UNTRUSTED, self.untrusted_bound, binned)


def calibrate(
    errors: np.ndarray,
    signal: np.ndarray,
    untrusted: np.ndarray,
    coverage: float = 0.9,
    bins: int = 3,
) -> BinnedBound:
    """Per-bin conformal bounds of one error from N validation answers.

    Args:
        errors: [N] errors >= 0 of the validation answers; +inf for a failed answer
            (it counts, as the largest error).
        signal: [N] trust signal, higher = more trusted; NaN where an answer has none.
        untrusted: [N] whether each answer fell back.
        coverage: the probability, in LEAST_COVERAGE .. MOST_COVERAGE, that a new
            answer's error is within its bound.
        bins: the most bins; fewer are made when each would hold under
            `answers_per_bin(coverage)` answers.

    Returns:
        The bounds, grouped as the module's note says.

    Raises:
        ConfigError: coverage outside LEAST_COVERAGE .. MOST_COVERAGE or bins below 1.
        DataError: lengths differ, no answers, or an error is NaN or negative.
    """
    coverage, bins = checked_options(coverage, bins)
    errors, signal, untrusted = checked_answers(errors, signal, untrusted)
    least = answers_per_bin(coverage)
    scored = np.isfinite(signal) & ~untrusted
    count = min(bins, int(scored.sum()) // least)
    edges = bin_edges(np.sort(signal[scored]), max(1, count), least)
    groups = _groups(edges, signal, untrusted)
    bounds = np.array(
        [conformal_bound(errors[groups == b], coverage) for b in range(len(edges) + 1)]
    )
    # Monotone repair: a less trusted bin's bound is at least every more trusted bin's
    # (a running max from the most trusted bin down). Each bin's bound only rises, so
    # each keeps its coverage guarantee, and a higher signal never means a wider bound.
    bounds = np.maximum.accumulate(bounds[::-1])[::-1]
    counts = np.bincount(groups[groups != UNTRUSTED], minlength=len(bounds)).astype(np.int64)
    untrusted_errors = errors[groups == UNTRUSTED]
    return BinnedBound(
        edges=edges,
        bounds=bounds,
        counts=counts,
        untrusted_bound=conformal_bound(untrusted_errors, coverage),
        untrusted_count=len(untrusted_errors),
    )


def bin_edges(ordered: np.ndarray, count: int, least: int) -> np.ndarray:
    """Edges cutting the sorted finite signals `ordered` into `count` equal-count bins.

    Each edge lies halfway between the last signal below it and the first above. Tied
    signals cannot be split, so a bin may come out short; a bin with fewer than `least`
    answers is merged into its smaller neighbour until none is (or one bin is left).
    """
    if count <= 1:
        return np.zeros(0)
    cuts = [round(k * len(ordered) / count) for k in range(1, count)]
    # Halves first: the sum of two large signals could overflow.
    edges = np.unique([ordered[c - 1] / 2 + ordered[c] / 2 for c in cuts])
    while len(edges):
        # A bin ends below its upper edge: a signal equal to an edge is in the bin above.
        ends = np.searchsorted(ordered, edges, side="left")
        sizes = np.diff(ends, prepend=0, append=len(ordered))
        small = int(np.argmin(sizes))
        if sizes[small] >= least:
            break
        if small == 0:
            drop = 0
        elif small == len(sizes) - 1 or sizes[small - 1] <= sizes[small + 1]:
            drop = small - 1
        else:
            drop = small
        edges = np.delete(edges, drop)
    return edges


def checked_coverage(
    coverage: object, key: str, error: type[ConfigError] | type[DataError]
) -> float:
    """`coverage` as a float in LEAST_COVERAGE .. MOST_COVERAGE, or an `error` naming
    `key` (a ConfigError for an option, a DataError for a stored value)."""
    if isinstance(coverage, bool) or not isinstance(coverage, (int, float, np.floating)):
        raise error(f"{key} must be a number, got {coverage!r}")
    if not LEAST_COVERAGE <= coverage <= MOST_COVERAGE:
        raise error(
            f"{key} must be between {LEAST_COVERAGE:g} and {MOST_COVERAGE:g} (e.g. 0.9), "
            f"got {coverage}"
        )
    return float(coverage)


def checked_options(coverage: float, bins: int) -> tuple[float, int]:
    """coverage in LEAST_COVERAGE .. MOST_COVERAGE and bins >= 1, or a ConfigError
    naming the option."""
    coverage = checked_coverage(coverage, "calibrate.coverage", ConfigError)
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise ConfigError(f"calibrate.bins must be a whole number >= 1, got {bins!r}")
    return float(coverage), int(bins)


def checked_answers(
    errors: np.ndarray, signal: np.ndarray, untrusted: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The validation answers as [N] float64, float64 and bool arrays, or a DataError."""
    errors = np.asarray(errors, dtype=np.float64)
    signal = np.asarray(signal, dtype=np.float64)
    untrusted = np.asarray(untrusted)
    if errors.ndim != 1 or signal.ndim != 1 or untrusted.ndim != 1:
        raise DataError(
            "calibrate: errors, signal and untrusted must be vectors, got shapes "
            f"{list(errors.shape)}, {list(signal.shape)} and {list(untrusted.shape)}"
        )
    if not len(errors) == len(signal) == len(untrusted):
        raise DataError(
            f"calibrate: {len(errors)} errors, {len(signal)} signals and {len(untrusted)} "
            "fell-back flags (one of each per validation answer)"
        )
    if len(errors) == 0:
        raise DataError("calibrate: no validation answers to calibrate on")
    if untrusted.dtype != bool:
        raise DataError(f"calibrate: untrusted must be booleans, got {untrusted.dtype}")
    if np.isnan(errors).any():
        raise DataError("calibrate: errors hold NaN (a failed answer's error is +inf)")
    if (errors < 0).any():
        raise DataError(f"calibrate: errors must be >= 0, got {errors.min()}")
    return errors, signal, untrusted


@dataclass(frozen=True)
class ErrorBounds:
    """A model's calibrated bounds of position and orientation errors."""

    coverage: float  # e.g. 0.9
    signal: str  # one of SIGNALS
    position: BinnedBound
    orientation: BinnedBound
    validation_size: int

    def state(self) -> dict[str, torch.Tensor]:
        """Plain tensors, keys prefixed "bounds.", for a weights-only model file."""
        state = {
            "bounds.coverage": torch.tensor(float(self.coverage), dtype=torch.float64),
            "bounds.signal": torch.tensor(SIGNALS.index(self.signal), dtype=torch.int64),
            "bounds.validation_size": torch.tensor(int(self.validation_size), dtype=torch.int64),
        }
        for name, binned in (("position", self.position), ("orientation", self.orientation)):
            prefix = f"bounds.{name}."
            # Copies: torch cannot share a read-only array's memory.
            state[prefix + "edges"] = torch.from_numpy(binned.edges.copy())
            state[prefix + "bounds"] = torch.from_numpy(binned.bounds.copy())
            state[prefix + "counts"] = torch.from_numpy(binned.counts.copy())
            state[prefix + "untrusted_bound"] = torch.tensor(
                binned.untrusted_bound, dtype=torch.float64
            )
            state[prefix + "untrusted_count"] = torch.tensor(
                binned.untrusted_count, dtype=torch.int64
            )
        return state

    @classmethod
    def from_state(cls, state: Mapping[str, torch.Tensor], label: str) -> ErrorBounds:
        """What `state` returned, every tensor checked first (a model file is data from
        anyone). Keys without the "bounds." prefix are ignored.

        Raises:
            DataError: starting with `{label}: ` and naming the tensor that is missing,
                of another dtype or shape, or holds an impossible value.
        """
        if not isinstance(state, Mapping):
            raise DataError(f"{label}: bounds state must be a mapping of tensors")
        coverage = float(_scalar(state, "bounds.coverage", torch.float64, label))
        # Any probability loads (an older relocfw calibrated anywhere in (0, 1)); the
        # sane range is calibration's to keep, and every finite bound is held to the
        # answers behind it below, whatever the coverage.
        if not 0 < coverage < 1:
            raise DataError(f"{label}: bounds.coverage must be in (0, 1), got {coverage}")
        code = int(_scalar(state, "bounds.signal", torch.int64, label))
        if not 0 <= code < len(SIGNALS):
            raise DataError(
                f"{label}: bounds.signal must be 0..{len(SIGNALS) - 1} ({', '.join(SIGNALS)}), "
                f"got {code}"
            )
        size = int(_scalar(state, "bounds.validation_size", torch.int64, label))
        if size < 1:
            raise DataError(f"{label}: bounds.validation_size must be >= 1, got {size}")
        binned = {
            name: _binned_of(state, f"bounds.{name}.", label, size, coverage) for name in _ERRORS
        }
        return cls(
            coverage=coverage,
            signal=SIGNALS[code],
            position=binned["position"],
            orientation=binned["orientation"],
            validation_size=size,
        )

    def describe(self) -> str:
        """One line for logs: coverage, validation size, signal, and each error's
        bounds from the most trusted bin's to the least trusted's."""
        count = len(self.position.bounds)
        parts = [
            f"{self.coverage * 100:g}% bounds from {self.validation_size} validation queries "
            f"({self.signal}, {count} bin{'s' if count != 1 else ''}): "
            f"position {_span(self.position.bounds)} m, "
            f"orientation {_span(self.orientation.bounds)} deg"
        ]
        if self.position.untrusted_count or self.orientation.untrusted_count:
            parts.append(
                f"; fell back or no signal ({self.position.untrusted_count}): "
                f"position {_number(self.position.untrusted_bound)} m, "
                f"orientation {_number(self.orientation.untrusted_bound)} deg"
            )
        return "".join(parts)


_ERRORS = ("position", "orientation")


def _number(value: float) -> str:
    return "inf" if math.isinf(value) else f"{value:.3g}"


def _span(bounds: np.ndarray) -> str:
    """The most trusted bin's bound to the least trusted's (bounds fall with trust)."""
    tightest, widest = _number(bounds[-1]), _number(bounds[0])
    return tightest if tightest == widest else f"{tightest}-{widest}"


def _shape(value: object) -> str:
    if isinstance(value, torch.Tensor):
        return f"shape {list(value.shape)}"
    return "nothing" if value is None else f"a {type(value).__name__}"


def _array(
    state: Mapping[str, torch.Tensor], key: str, dtype: torch.dtype, label: str
) -> np.ndarray:
    """state[key] as a numpy copy, or a DataError if missing or not of `dtype`."""
    value = state.get(key)
    if not isinstance(value, torch.Tensor):
        raise DataError(f"{label}: {key} must be a tensor, got {_shape(value)}")
    if value.dtype != dtype or value.layout != torch.strided or value.is_meta:
        raise DataError(f"{label}: {key} must be a dense {dtype} tensor, got {value.dtype}")
    return value.detach().cpu().numpy().copy()


def _scalar(
    state: Mapping[str, torch.Tensor], key: str, dtype: torch.dtype, label: str
) -> np.ndarray:
    value = _array(state, key, dtype, label)
    if value.shape != ():
        raise DataError(f"{label}: {key} must be a single number (shape []), got {value.shape}")
    if np.isnan(value):
        raise DataError(f"{label}: {key} is NaN")
    return value


def _binned_of(
    state: Mapping[str, torch.Tensor], prefix: str, label: str, size: int, coverage: float
) -> BinnedBound:
    """One error's BinnedBound from the tensors under `prefix`, each checked: a finite
    bound only where its group's answers can give one at `coverage` (calibration
    gives inf where they cannot, so a finite one there is a forged claim)."""
    keys = {name: prefix + name for name in ("edges", "bounds", "counts")}
    bounds = _array(state, keys["bounds"], torch.float64, label)
    if bounds.ndim != 1 or not 1 <= len(bounds) <= MOST_BINS:
        raise DataError(
            f"{label}: {keys['bounds']} must be [B] with B in 1..{MOST_BINS}, got {bounds.shape}"
        )
    edges = _array(state, keys["edges"], torch.float64, label)
    if edges.shape != (len(bounds) - 1,):
        raise DataError(
            f"{label}: {keys['edges']} must be [{len(bounds) - 1}] (one fewer than "
            f"{keys['bounds']}), got {list(edges.shape)}"
        )
    counts = _array(state, keys["counts"], torch.int64, label)
    if counts.shape != bounds.shape:
        raise DataError(
            f"{label}: {keys['counts']} must be [{len(bounds)}] like {keys['bounds']}, "
            f"got {list(counts.shape)}"
        )
    if not np.isfinite(edges).all() or (np.diff(edges) < 0).any():
        raise DataError(f"{label}: {keys['edges']} must be finite and non-decreasing")
    if np.isnan(bounds).any() or (bounds < 0).any():
        raise DataError(f"{label}: {keys['bounds']} must be >= 0 (inf allowed), not NaN")
    if (np.diff(bounds) > 0).any():
        raise DataError(
            f"{label}: {keys['bounds']} must not rise with trust (bin 0 is the least trusted)"
        )
    if (counts < 0).any():
        raise DataError(f"{label}: {keys['counts']} must be >= 0")
    untrusted_bound = float(_scalar(state, prefix + "untrusted_bound", torch.float64, label))
    if untrusted_bound < 0:
        raise DataError(f"{label}: {prefix}untrusted_bound must be >= 0, got {untrusted_bound}")
    untrusted_count = int(_scalar(state, prefix + "untrusted_count", torch.int64, label))
    if untrusted_count < 0:
        raise DataError(f"{label}: {prefix}untrusted_count must be >= 0, got {untrusted_count}")
    # Every validation answer is in exactly one group.
    # Python integers: a forged count near 2**63 must not wrap around in an int64 sum.
    total = sum(int(c) for c in counts)
    if total + untrusted_count != size:
        raise DataError(
            f"{label}: {keys['counts']} ({total}) and {prefix}untrusted_count "
            f"({untrusted_count}) must add up to bounds.validation_size ({size})"
        )
    groups = [
        (f"{keys['bounds']}[{b}]", float(bounds[b]), int(counts[b])) for b in range(len(counts))
    ]
    groups.append((f"{prefix}untrusted_bound", untrusted_bound, untrusted_count))
    for key, bound, count in groups:
        if math.isfinite(bound) and not supports(count, coverage):
            raise DataError(
                f"{label}: {key} is {bound:g} from {count} answer{'s' if count != 1 else ''}; "
                f"at bounds.coverage {coverage:g} a finite bound needs at least "
                f"{least_answers(coverage)} (calibration gives inf)"
            )
    return BinnedBound(edges, bounds, counts, untrusted_bound, untrusted_count)
