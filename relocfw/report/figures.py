"""The comparison figures, drawn as PNG files.

matplotlib's object API only (`matplotlib.figure.Figure`, never pyplot): no display
is needed, no backend is chosen and no figure is registered anywhere, so importing
relocfw leaves the user's matplotlib as it was.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from sklearn.manifold import TSNE

from relocfw.core.atomic_files import atomic_write
from relocfw.data.frames import Frame, positions_of
from relocfw.report.evaluation import MethodResult, uncertainty_signal_of
from relocfw.report.units import METRES, PositionUnit


def new_figure(
    size: tuple[float, float], rows: int = 1, columns: int = 1, **options: Any
) -> tuple[Figure, Any]:
    """A figure of `size` inches with a grid of axes (`Figure.subplots`'s `options`),
    outside pyplot: nothing global refers to it, so it needs no closing."""
    figure = Figure(figsize=size)
    return figure, figure.subplots(rows, columns, **options)


def save(figure: Figure, path: Path) -> Path:
    """Write `figure` to `path` as a PNG, all or nothing."""
    with atomic_write(path, "wb") as stream:
        figure.savefig(stream, format="png", dpi=110, bbox_inches="tight")
    return Path(path)


HISTOGRAM_KINDS = {
    # kind: (good threshold, bad threshold, minimum axis extent); metres for position
    "position": (0.5, 1.0, 1.0),
    "orientation": (15.0, 20.0, 20.0),
}


def error_histogram(
    results: Sequence[MethodResult],
    kind: str,
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """Figure 7: histogram of position or orientation errors, methods overlaid.

    The legend gives each method's share under the paper's good threshold
    (0.5 m / 15 deg) and over its bad one (1.0 m / 20 deg). Positions in another
    `unit` than metres get no thresholds: 0.5 of an arbitrary unit means nothing.
    """
    good, bad, extent = HISTOGRAM_KINDS[kind]
    if kind == "orientation":
        label, suffix = "orientation error (deg)", "°"
    else:
        label, suffix = f"position error ({unit.name})", f" {unit.name}"
    thresholds = kind == "orientation" or unit.metric
    errors = [
        r.position_errors() if kind == "position" else r.orientation_errors() for r in results
    ]
    finite = [e[np.isfinite(e)] for e in errors]
    top = max([extent, *(float(f.max()) for f in finite if len(f))])
    bins = np.linspace(0, top, 30)
    figure, axis = new_figure((7, 4.5))
    for result, error in zip(results, errors, strict=True):
        parts = []
        if thresholds:
            under, over = np.mean(error < good), np.mean(error > bad)
            parts.append(f"{under:.0%} < {good:g}{suffix}, {over:.0%} > {bad:g}{suffix}")
        failed = int(np.sum(~np.isfinite(error)))
        if failed:
            parts.append(f"{failed} failed (in the last bin)")
        shares = ", ".join(parts)
        # A failed query (inf) is drawn in the last bin, never left out.
        axis.hist(
            np.minimum(error, top),
            bins=bins,
            histtype="step",
            linewidth=1.8,
            label=f"{result.method}: {shares}" if shares else result.method,
        )
    for value in (good, bad) if thresholds else ():
        axis.axvline(value, color="grey", linestyle=":", linewidth=1)
    axis.set_xlabel(label)
    axis.set_ylabel("queries")
    axis.legend(fontsize=7)
    axis.set_title(f"{kind.capitalize()} error histogram {title}".strip())
    return save(figure, path)


def error_curves(
    results: Sequence[MethodResult], path: Path, title: str = "", unit: PositionUnit = METRES
) -> Path:
    """Figure 8: position and orientation error of every test image, in order."""
    figure, (top, bottom) = new_figure((12, 6), 2, 1, sharex=True)
    for axis, kind in ((top, "position"), (bottom, "orientation")):
        errors = [
            r.position_errors() if kind == "position" else r.orientation_errors() for r in results
        ]
        finite = [e[np.isfinite(e)] for e in errors]
        ceiling = max([1e-9, *(float(f.max()) for f in finite if len(f))]) * 1.05
        for result, error in zip(results, errors, strict=True):
            # Failed queries (inf) are drawn at the top of the axis with an x.
            (line,) = axis.plot(np.minimum(error, ceiling), linewidth=1.2, label=result.method)
            failed = np.flatnonzero(~np.isfinite(error))
            if len(failed):
                axis.plot(failed, np.full(len(failed), ceiling), "x", color=line.get_color())
    top.set_ylabel(f"position error ({unit.name})")
    bottom.set_ylabel("orientation error (deg)")
    bottom.set_xlabel("test image (trajectory order)")
    top.legend(fontsize=7)
    figure.suptitle(f"Per-image errors {title}".strip())
    return save(figure, path)


def trajectory_top_down(
    train: Sequence[Frame],
    results: Sequence[MethodResult],
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """Top-down (x, y) view: training path, test ground truth and each method's estimates."""
    figure, axis = new_figure((8, 7))
    train_xy = positions_of(train)[:, :2]
    axis.plot(*train_xy.T, ".", color="lightgrey", markersize=3, label="training poses")
    truth = np.stack([f.pose.position for f in results[0].frames])[:, :2]
    axis.plot(*truth.T, "-", color="black", linewidth=2, label="test ground truth")
    for result in results:
        estimates = np.stack([a.pose.position for a in result.answers])[:, :2]
        axis.plot(*estimates.T, "o", markersize=3, alpha=0.8, label=result.method)
    axis.set_aspect("equal")
    axis.set_xlabel(f"x ({unit.name})")
    axis.set_ylabel(f"y ({unit.name})")
    axis.legend(fontsize=7)
    axis.set_title(f"Trajectory, top-down {title}".strip())
    return save(figure, path)


def tsne_of_map(
    features: np.ndarray,
    centres: np.ndarray,
    labels: np.ndarray,
    path: Path,
    seed: int = 0,
    title: str = "",
) -> Path:
    """Figure 5: t-SNE of the standardised training descriptors and k-means centres.

    Descriptors are coloured by their cluster; centres are black crosses.
    """
    points = np.concatenate([features, centres])
    perplexity = float(min(30.0, max(2.0, (len(points) - 1) / 3)))
    embedded = TSNE(perplexity=perplexity, init="pca", random_state=seed).fit_transform(points)
    figure, axis = new_figure((7, 6))
    axis.scatter(*embedded[: len(features)].T, c=labels, cmap="tab20", s=8, alpha=0.7)
    axis.scatter(
        *embedded[len(features) :].T,
        marker="x",
        color="black",
        s=40,
        label=f"{len(centres)} k-means centres",
    )
    axis.legend(fontsize=8)
    axis.set_title(f"t-SNE of the map's descriptors {title}".strip())
    axis.set_xticks([])
    axis.set_yticks([])
    return save(figure, path)


def uncertainty_against_error(
    result: MethodResult,
    quality: dict,
    path: Path,
    title: str = "",
    unit: PositionUnit = METRES,
) -> Path:
    """The authors' view, one point per query: uncertainty against error (position and
    orientation), and each kind's sparsification curve against its oracle.

    The uncertainty is the method's signal (relocfw.report.evaluation
    .uncertainty_signal_of): a sampled method's spreads, or a refined method's
    -confidence (the same for both kinds), where fallbacks are drawn as crosses at
    their own -confidence (the measures rank them as the most uncertain).
    """
    figure, axes = new_figure((11, 8), 2, 2)
    signal = uncertainty_signal_of(result)
    confidence = np.array([a.refine_confidence for a in result.answers], dtype=np.float64)
    spreads = {
        "position": np.array([a.position_spread for a in result.answers]),
        "orientation": np.array([a.orientation_spread_deg for a in result.answers]),
    }
    by_confidence = signal is not None and signal.from_confidence
    fell_back = np.array([a.fell_back for a in result.answers], dtype=bool)
    errors = {"position": result.position_errors(), "orientation": result.orientation_errors()}
    for row, (kind, name) in enumerate((("position", unit.name), ("orientation", "deg"))):
        measures = quality[kind]
        scatter, curves = axes[row]
        finite = np.isfinite(errors[kind])
        if by_confidence:
            # -confidence, not the ranked value: the lift of fallbacks has no unit.
            accepted, dropped = finite & ~fell_back, finite & fell_back
            scatter.scatter(-confidence[accepted], errors[kind][accepted], s=10, label="refined")
            if dropped.any():
                scatter.scatter(
                    -confidence[dropped],
                    errors[kind][dropped],
                    s=24,
                    marker="x",
                    label="fell back (ranked most uncertain)",
                )
                scatter.legend(fontsize=8)
            scatter.set_xlabel("-confidence (the refiner's unit, e.g. -PnP inliers)")
        else:
            scatter.scatter(spreads[kind][finite], errors[kind][finite], s=10)
            scatter.set_xlabel(f"{kind} spread ({name})")
        scatter.set_ylabel(f"{kind} error ({name})")
        scatter.set_title(f"Spearman {measures['spearman_spread_error']:.2f}", fontsize=9)
        sparsification = measures["sparsification"]
        curves.plot(
            sparsification["fractions"],
            sparsification["by_uncertainty"],
            label="by -confidence" if by_confidence else "by spread",
        )
        curves.plot(sparsification["fractions"], sparsification["oracle"], label="by true error")
        curves.set_xlabel("fraction of queries removed (most uncertain first)")
        curves.set_ylabel(f"median {kind} error of the rest ({name})")
        curves.set_title(f"AUSE {measures['ause']:.3g} {name}", fontsize=9)
        curves.legend(fontsize=8)
    signal_name = signal.name if signal is not None else "uncertainty"
    figure.suptitle(f"{result.method}: {signal_name} against error {title}".strip())
    figure.tight_layout()
    return save(figure, path)


def training_curve(
    history: dict[str, list[float]], path: Path, title: str = "", unit: PositionUnit = METRES
) -> Path:
    """Per-step losses of a training run: the total and each head's (log scale), the
    main head's errors (positions in the training poses' `unit`), and the learning
    rate with any learned loss weights."""
    figure, (losses, errors, schedule) = new_figure((15, 4), 1, 3)
    steps = np.arange(1, len(history.get("loss", [])) + 1)
    for name in ("loss", "main", "aux1", "aux2"):
        if history.get(name):
            losses.plot(steps, history[name], label=name, linewidth=0.8)
    losses.set_yscale("log")
    losses.set_title("loss (total and weighted per head)", fontsize=9)
    losses.legend(fontsize=8)
    if history.get("main_position_m"):
        errors.plot(
            steps, history["main_position_m"], label=f"position ({unit.name})", linewidth=0.8
        )
        errors.plot(steps, history["main_orientation"], label="||q - q^||", linewidth=0.8)
        errors.legend(fontsize=8)
    errors.set_title("main head's batch errors", fontsize=9)
    if history.get("lr"):
        schedule.plot(steps, history["lr"], label="learning rate", color="black")
        schedule.set_yscale("log")
    weights = schedule.twinx()
    for name in ("s_position", "s_orientation"):
        if history.get(name):
            weights.plot(steps, history[name], label=name, linewidth=0.8)
    if history.get("s_position"):
        weights.legend(fontsize=8, loc="lower left")
        weights.set_ylabel("learned s (log variance)")
    schedule.set_title("learning rate and learned loss weights", fontsize=9)
    for axis in (losses, errors, schedule):
        axis.set_xlabel("step")
    figure.suptitle(f"training {title}".strip())
    figure.tight_layout()
    return save(figure, path)
