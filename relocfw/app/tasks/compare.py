"""task=compare: every method of compare.methods on every scene, for every training
seed; the Table-1 style comparison, per-scene tables, figures and uncertainty checks.

compare.methods' rows (name: overrides on top of the command line's) come from the
methods group (conf/methods/*.yaml, or a user's own file). A row in the old spellings
(`scoring=shared`) is read in the new ones (`query.scoring=shared`), with one note.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from relocfw.app.engines import on_engine, wanted_engine
from relocfw.app.hydra_errors import COMPOSITION_ERRORS, one_line
from relocfw.app.methods import build, build_method, scene_name
from relocfw.app.results import fit_method, run_method, safe_name, write_results
from relocfw.app.spellings import rewrite
from relocfw.app.split_record import (
    check_validation_run,
    split_line,
    split_record,
    validation_for_option,
)
from relocfw.app.splits import load_split, write_skipped
from relocfw.app.training_runs import prepare_model
from relocfw.app.validation_block import calibrate_options, carve_validation
from relocfw.core.errors import ConfigError
from relocfw.core.json_output import strict_json
from relocfw.core.options import integer_at_least
from relocfw.core.pipeline import Relocalizer
from relocfw.data.frames import Frame, mean_pose
from relocfw.model.checkpoints import write_text_atomic
from relocfw.model.distributed import World
from relocfw.report import figures
from relocfw.report.comparison import (
    as_csv,
    as_markdown,
    crop_seed_markdown,
    crop_seed_spread,
    median_errors,
    table_rows,
    uncertainty_check,
)
from relocfw.report.evaluation import (
    MethodResult,
    constant_answer,
    evaluate,
    evaluate_round_robin,
    uncertainty_of,
)
from relocfw.report.seed_comparison import SeedResults, seed_comparison, seed_footnote, seed_rows
from relocfw.report.units import (
    METRES,
    PositionUnit,
    json_note,
    relabel_table,
    relabel_tree,
    text_note,
    unit_of,
)


def compose_method(overrides: list[str], name: str) -> tuple[DictConfig, Mapping[str, str]]:
    try:
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
    except COMPOSITION_ERRORS as error:
        raise ConfigError(f"compare.methods.{name}: {one_line(error)}") from error
    return cfg, cfg.hydra.runtime.choices


def row_label(name: str, overrides: list[str], method_cfg: DictConfig) -> str:
    """The row's name, saying so when dropout is sampled although the row did not ask.

    `backbone.mc_samples=N` on the command line applies to every row: a row called
    "PoseNet" would otherwise hide that its answers are Monte Carlo means.
    """
    samples = int(method_cfg.backbone.get("mc_samples", 0))
    asked = any(o.startswith(("backbone.mc_samples", "backbone=")) for o in overrides)
    return f"{name} (x{samples} MC dropout)" if samples and not asked else name


def plain(value: Any) -> Any:
    """An option's value with OmegaConf's lists and dicts as Python's."""
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def seed_list(cfg: DictConfig, key: str) -> list[int] | None:
    """compare.<key> as distinct integers >= 0; None when unset."""
    value = cfg.compare.get(key)
    if value is None:
        return None
    if not OmegaConf.is_list(value):
        raise ConfigError(f"compare.{key} must be a list such as [0,1,2], got {value}")
    seeds = [integer_at_least(f"compare.{key}", s, 0) for s in value]
    if not seeds or len(set(seeds)) != len(seeds):
        raise ConfigError(f"compare.{key} must be distinct integers, got {list(value)}")
    return seeds


def training_seeds(cfg: DictConfig) -> list[int]:
    """compare.seeds, or the run's own seed when unset."""
    return seed_list(cfg, "seeds") or [int(cfg.seed)]


def method_rows(cfg: DictConfig) -> dict[str, list[str]]:
    """compare.methods: name -> overrides, each list in the new spellings (one note per
    old key on stderr)."""
    methods = cfg.compare.get("methods")
    if not methods:
        raise ConfigError("compare.methods is empty")
    rows, notes = {}, {}
    for name, overrides in OmegaConf.to_container(methods, resolve=True).items():
        if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
            raise ConfigError(
                f"compare.methods.{name} must be a list of overrides such as "
                f"[crop=centre, index=kmeans], got {overrides!r}"
            )
        try:
            rows[str(name)], found = rewrite(overrides)
        except ConfigError as error:
            raise ConfigError(f"compare.methods.{name}: {error}") from error
        for spelled in found:
            notes.setdefault(spelled.old, spelled.note(f"compare.methods.{name}"))
    for note in notes.values():
        print(note, file=sys.stderr)
    return rows


def scene_list(cfg: DictConfig) -> list[str | None]:
    """compare.scenes; [None] (the dataset as set) when unset."""
    scenes = cfg.compare.get("scenes")
    if scenes is None:
        return [None]
    if not OmegaConf.is_list(scenes) or not scenes:
        raise ConfigError(f"compare.scenes must be a list such as [chess, fire], got {scenes}")
    return [str(scene) for scene in scenes]


def plan(
    methods: Mapping[str, list[str]], scenes: Sequence[str | None], seeds: list[int]
) -> tuple[dict, dict[str, str]]:
    """Every (seed, scene, method)'s composed config and choices, and each row's name.

    Composed before any work, so that a typo in any row fails before hours of training.
    """
    overrides = HydraConfig.get().overrides
    base = [o for o in overrides.task if not o.lstrip("~+").startswith(("task=", "compare."))]
    # A user's own methods file is found through hydra.searchpath, which Hydra keeps
    # apart from the task's overrides: each row must be composed with it too.
    base += [o for o in overrides.hydra if o.lstrip("+").startswith("hydra.searchpath=")]
    plans, rows = {}, {}
    for seed in seeds:
        for scene in scenes:
            scene_override = [f"dataset.scene={scene}"] if scene is not None else []
            for name, overrides in methods.items():
                composed = base + scene_override + overrides + [f"seed={seed}"]
                method_cfg, choices = compose_method(composed, name)
                if len(seeds) > 1 and int(method_cfg.train.seed) != seed:
                    # train.seed=N on the command line would pin every "seed" to one
                    # model: a spread of zero and a meaningless test.
                    raise ConfigError(
                        f"compare.seeds: train.seed is pinned to {method_cfg.train.seed}; "
                        "drop train.seed= so each training seed trains its own model"
                    )
                plans[seed, scene, name] = (method_cfg, choices)
                rows[name] = row_label(name, overrides, method_cfg)
    return plans, rows


def one_calibration(plans: Mapping[tuple, tuple[DictConfig, Any]]) -> None:
    """Refuse rows whose `calibrate:` options differ: the validation block is carved
    once per scene, before the rows train, so it cannot differ per row."""
    found = {}
    for (_, _, name), (method_cfg, _) in plans.items():
        found.setdefault(calibrate_options(method_cfg), name)
    if len(found) > 1:
        names = ", ".join(repr(name) for name in found.values())
        raise ConfigError(
            f"compare rows {names} set different calibrate.* options; the validation "
            "block is one per scene: set calibrate.* on the command line, for every row"
        )


def one_dataset(plans: Mapping[tuple, tuple[DictConfig, Any]]) -> None:
    """Refuse rows whose `dataset.*` options differ: each scene's frames are loaded
    once, with the first row's options (of the first training seed: every seed answers
    the same frames), and shared by every row, so a row's own dataset.* override would
    silently do nothing. Where the caches live and quiet do not change the frames."""
    found: dict[Any, dict[str, str]] = {}
    for (seed, scene, name), (method_cfg, _) in plans.items():
        values = OmegaConf.to_container(method_cfg.dataset, resolve=True)
        kept = {k: v for k, v in values.items() if k not in ("cache_dir", "quiet")}
        options = json.dumps(kept, default=str, sort_keys=True)
        # Per training seed: a dataset option may follow the seed (the synthetic
        # scene's `seed: ${seed}`), and the rows of one seed must agree.
        found.setdefault((seed, scene), {}).setdefault(options, name)
    for names in found.values():
        if len(names) > 1:
            rows = ", ".join(repr(name) for name in names.values())
            raise ConfigError(
                f"compare rows {rows} set different dataset.* options; every row answers "
                "the same frames, loaded once per scene: set dataset.* on the command line "
                "(and run task=compare once per setting to compare them)"
            )


def run(cfg: DictConfig, device: torch.device, world: World | None) -> None:
    """Every method of compare.methods on every scene, for every training seed.

    Each (seed, scene, method) model is trained once (or found in the cache); with
    several seeds, each seed's full comparison goes to seed_<n>/ and the top-level
    comparison files hold the spread over seeds and the paired tests. Scenes are
    named as the dataset names them (dataset.scene, e.g. redkitchen), else by the
    dataset (synthetic).
    """
    methods = method_rows(cfg)
    scenes = scene_list(cfg)
    reference = str(cfg.compare.get("reference"))
    if reference not in methods:
        raise ConfigError(f"compare.reference={reference!r} is not in compare.methods")
    seeds = training_seeds(cfg)
    crop_seeds = seed_list(cfg, "crop_seeds") or []
    validation_for = validation_for_option(plain(cfg.compare.get("validation_for")))
    quiet = bool(cfg.quiet)
    round_robin = cfg.compare.get("round_robin", False)
    if not isinstance(round_robin, bool):
        raise ConfigError(f"compare.round_robin must be true or false, got {round_robin!r}")
    plans, rows = plan(methods, scenes, seeds)
    one_calibration(plans)
    one_dataset(plans)
    if round_robin:
        for (_, _, name), (method_cfg, _) in plans.items():
            # Checked before any row trains: taking turns times one query at a time.
            at_once = method_cfg.query.get("queries_at_once")
            if at_once is not None and int(at_once) != 1:
                raise ConfigError(
                    f"compare.round_robin times one query at a time, but row {name!r} "
                    f"answers {at_once} at once (query.queries_at_once): set it to 1 or "
                    "compare.round_robin=false"
                )
    for (_, _, name), (method_cfg, _) in plans.items():
        try:  # a row's engine options, before any row trains
            wanted_engine(method_cfg, device)
        except ConfigError as error:
            raise ConfigError(f"compare row {name!r}: {error}") from error
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    results = {seed: {} for seed in seeds}
    seed_runs = {seed: {} for seed in seeds}
    maps = {seed: {} for seed in seeds}
    training, floors, splits = {}, {}, {}
    units: dict[str, PositionUnit] = {}
    for scene in scenes:
        first_cfg, first_choices = plans[seeds[0], scene, next(iter(methods))]
        dataset = build(first_cfg, "dataset", first_choices["dataset"])
        label = scene_name(first_cfg, first_choices)
        units[label] = unit_of(dataset)
        unit = one_unit(units)  # a mixed list fails before this scene trains
        train = load_split(dataset, "train", quiet)
        test = load_split(dataset, "test", quiet)
        if validation_for is not None:  # before any row of the scene trains
            check_validation_run(dataset, train[0], test[0], validation_for)
        train, calibration = carve_validation(first_cfg, train)
        write_skipped(dataset, run_dir)
        splits[label] = split_record(dataset, train[0], test[0], calibration, validation_for)
        training[label] = train[0]
        floors[label] = constant_answer("mean training pose", mean_pose(train[0]), test[0])
        for seed in seeds:
            if len(seeds) > 1:
                print(f"\n== {label}: training seed {seed} ==")
            results[seed][label], seed_runs[seed][label] = {}, {}
            maps[seed][label] = None
            fitted: dict[str, Fitted] = {}
            for name in methods:
                method_cfg, choices = plans[seed, scene, name]
                method = build_method(method_cfg, choices, label=rows[name])
                method.index.check_map_size(len(train[0]))
                # One curve per distinct model: rows sharing a model share its file.
                seed_dir = run_dir / f"seed_{seed}" if len(seeds) > 1 else run_dir
                checkpoint = prepare_model(
                    method_cfg, method, train, device, curve_dir=seed_dir, unit=unit_of(dataset)
                )
                relocalizer = on_engine(
                    method_cfg, method.relocalizer(device), checkpoint, device, train[1]
                )
                if round_robin:
                    # Every row fitted first, all held at once; the queries then take
                    # turns (below).
                    features = fit_method(rows[name], relocalizer, train, quiet, calibration)
                    fitted[name] = Fitted(method_cfg, choices, method, relocalizer, features)
                    continue
                result, features = run_method(
                    rows[name], relocalizer, train, test, quiet, calibration
                )
                results[seed][label][rows[name]] = result
                # Row after row, nothing is held: a row's map is freed before the next.
                row = Fitted(method_cfg, choices, method, relocalizer, features)
                seed_runs[seed][label] |= crop_seed_runs(
                    rows[name], row, result, test, crop_seeds, quiet
                )
                maps[seed][label] = maps[seed][label] or kmeans_map(row)
            if round_robin:
                turns = {rows[n]: row.relocalizer for n, row in fitted.items()}
                print(f"{label}: {len(turns)} methods take turns, query by query")
                results[seed][label] = evaluate_round_robin(turns, *test, quiet=quiet)
                for name, row in fitted.items():
                    result = results[seed][label][rows[name]]
                    seed_runs[seed][label] |= crop_seed_runs(
                        rows[name], row, result, test, crop_seeds, quiet
                    )
                    maps[seed][label] = maps[seed][label] or kmeans_map(row)
                fitted.clear()
    for seed in seeds:
        write_comparison(
            results[seed],
            training,
            maps[seed],
            rows[reference],
            run_dir / f"seed_{seed}" if len(seeds) > 1 else run_dir,
            seed=seed,
            seed_runs=seed_runs[seed],
            unit=unit,
            splits=splits,
        )
    if len(seeds) > 1:
        write_seed_comparison(
            results,
            floors,
            rows[reference],
            run_dir,
            bootstrap_seed=seeds[0],
            unit=unit,
            splits=splits,
        )
    if unit.note:
        print(f"note: {unit.note}")


@dataclass(frozen=True)
class Fitted:
    """One compare row, built and fitted: what its crop-seed reruns and the map need."""

    method_cfg: DictConfig
    choices: Mapping[str, str]
    method: Any
    relocalizer: Relocalizer
    features: np.ndarray


def crop_seed_runs(
    label: str,
    row: Fitted,
    result: MethodResult,
    test: tuple,
    crop_seeds: list[int],
    quiet: bool,
) -> dict[str, dict[int, MethodResult]]:
    """The row's reruns over compare.crop_seeds where its crop search has a seed (the
    GA), keyed by the row's label; empty otherwise."""
    if "seed" not in row.method_cfg.crop or len(crop_seeds) < 2:
        return {}
    runs = rerun_crop_seeds(
        row.method_cfg, row.choices, row.relocalizer, result, test, crop_seeds, quiet
    )
    return {label: runs}


def kmeans_map(row: Fitted) -> MapView | None:
    """The map figure's data from a row whose index has k-means centres; None else."""
    index = row.method.index
    if not hasattr(index, "centres"):
        return None
    return MapView(index.zscore(row.features), index.centres, index.assign(row.features))


def one_unit(units: Mapping[str, PositionUnit]) -> PositionUnit:
    """The positions' unit shared by every scene: one table cannot mix metres with
    model units (its average row would add them)."""
    if len({unit.metric for unit in units.values()}) > 1:
        named = ", ".join(f"{scene}: {unit.name}" for scene, unit in units.items())
        raise ConfigError(f"compare.scenes measure positions in different units ({named})")
    return next(iter(units.values()))


def rerun_crop_seeds(
    method_cfg: DictConfig,
    choices: Mapping[str, str],
    relocalizer: Relocalizer,
    result: MethodResult,
    test: tuple,
    crop_seeds: list[int],
    quiet: bool,
) -> dict[int, MethodResult]:
    """The method's test split again with each crop-search seed; model and map reused."""
    runs = {}
    configured = relocalizer.search
    try:
        for seed in crop_seeds:
            if seed == int(method_cfg.crop.seed):
                runs[seed] = result  # the run in the main table
                continue
            seeded = method_cfg.copy()
            seeded.crop.seed = seed
            relocalizer.search = build(seeded, "crop", choices["crop"])
            runs[seed] = evaluate(f"{result.method}, crop.seed={seed}", relocalizer, *test, quiet)
    finally:
        relocalizer.search = configured
    return runs


@dataclass(frozen=True)
class MapView:
    """What the t-SNE figure shows: standardised map descriptors and k-means centres."""

    features: np.ndarray
    centres: np.ndarray
    labels: np.ndarray


def write_comparison(
    results: Mapping[str, Mapping[str, MethodResult]],
    training_frames: Mapping[str, Sequence[Frame]],
    maps: Mapping[str, MapView | None],
    reference: str,
    run_dir: Path,
    seed: int = 0,
    seed_runs: Mapping[str, Mapping[str, Mapping[int, MethodResult]]] | None = None,
    unit: PositionUnit = METRES,
    splits: Mapping[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Table 1 (Markdown + CSV, printed), per-scene results and the five figures.

    Args:
        seed_runs: scene -> method -> crop-search seed -> result, for the methods
            whose crop search is randomised; their spread goes to crop_seeds.md and
            comparison.json.
        unit: the positions' unit; the Markdown files start with its note, the JSON
            carries it as `units_note`, the CSV has the unit in its column titles.
        splits: scene -> its split record (relocfw.app.split_record): comparison.json
            holds them as `splits`, each scene's summary JSON as `split`, and the
            Markdown files say them in one line per scene.

    Returns:
        What comparison.json holds.
    """
    run_dir = Path(run_dir)
    splits = splits or {}
    header, rows = table_rows(median_errors(results), reference, unit)
    markdown = as_markdown(header, rows)
    write_text_atomic(text_note(unit) + split_lines(splits) + markdown, run_dir / "comparison.md")
    write_text_atomic(as_csv(header, rows), run_dir / "comparison.csv")
    print(
        f"\nMedian position ({unit.name}) and orientation (deg) errors; "
        "average = mean over scenes\n"
    )
    print(split_lines(splits) + markdown)
    summary: dict[str, Any] = {**json_note(unit), "reference": reference, "scenes": {}}
    if splits:
        summary["splits"] = dict(splits)
    written = []
    for scene, by_method in results.items():
        name = safe_name(scene)
        method_results = list(by_method.values())
        floor = constant_answer(
            "mean training pose", mean_pose(training_frames[scene]), method_results[0].frames
        )
        table = write_results(
            [floor, *method_results], run_dir, name=f"_{name}", unit=unit, split=splits.get(scene)
        )
        print(f"{scene}:\n{table}\n")
        title = f"({scene})"
        out = run_dir / name
        written += [
            figures.error_histogram(
                method_results,
                "position",
                Path(f"{out}_position_error_histogram.png"),
                title,
                unit,
            ),
            figures.error_histogram(
                method_results,
                "orientation",
                Path(f"{out}_orientation_error_histogram.png"),
                title,
            ),
            figures.error_curves(method_results, Path(f"{out}_error_per_image.png"), title, unit),
            figures.trajectory_top_down(
                training_frames[scene],
                method_results,
                Path(f"{out}_trajectory_top_down.png"),
                title,
                unit,
            ),
        ]
        view = maps.get(scene)
        if view is not None:
            written.append(
                figures.tsne_of_map(
                    view.features,
                    view.centres,
                    view.labels,
                    Path(f"{out}_tsne_kmeans_map.png"),
                    seed=seed,
                    title=title,
                )
            )
        checks = {m: uncertainty_check(r) for m, r in by_method.items()}
        checks = {m: c for m, c in checks.items() if c is not None}
        measured = {m: uncertainty_of(r) for m, r in by_method.items()}
        measured = {m: u for m, u in measured.items() if u is not None}
        for method, (signal, quality) in measured.items():
            checks[method]["quality"] = quality
            written.append(
                figures.uncertainty_against_error(
                    by_method[method],
                    quality,
                    Path(f"{out}_{safe_name(method)}_uncertainty.png"),
                    title,
                    unit,
                )
            )
            print(
                f"{method} uncertainty quality ({scene}): AUSE position "
                f"{quality['position']['ause']:.3f} {unit.name}, orientation "
                f"{quality['orientation']['ause']:.2f} deg; Spearman(uncertainty, error) "
                f"({signal.name}) position "
                f"{quality['position']['spearman_spread_error']:.2f}, orientation "
                f"{quality['orientation']['spearman_spread_error']:.2f}"
            )
        for method, check in checks.items():
            print(
                f"{method} uncertainty ({scene}): median position error of the "
                f"{check['queries_per_group']} most uncertain queries "
                f"{check['most_uncertain_median_position_m']:.3f} {unit.name}, of the least "
                f"uncertain {check['least_uncertain_median_position_m']:.3f} {unit.name} "
                f"(rank correlation {check['spread_error_rank_correlation']:.2f})"
            )
        # Below the method names (a user's words), every key is a report key.
        summary["scenes"][scene] = {
            "uncertainty": {m: relabel_tree(c, unit) for m, c in checks.items()}
        }
    spreads = {
        scene: {method: crop_seed_spread(runs) for method, runs in by_method.items()}
        for scene, by_method in (seed_runs or {}).items()
        if by_method
    }
    if spreads:
        table = crop_seed_markdown(spreads, unit)
        write_text_atomic(text_note(unit) + split_lines(splits) + table, run_dir / "crop_seeds.md")
        print("\nSpread of the medians over crop-search seeds (same model and map):\n")
        print(table)
        for scene, by_method in spreads.items():
            summary["scenes"].setdefault(scene, {})["crop_seed_spread"] = {
                method: relabel_tree(spread, unit) for method, spread in by_method.items()
            }
    summary["figures"] = [str(p) for p in written]
    write_text_atomic(strict_json(summary), run_dir / "comparison.json")
    print(f"\ncomparison: {run_dir / 'comparison.md'}; figures: {len(written)} PNG in {run_dir}")
    return summary


def seed_tables(
    table: Mapping[str, Mapping[str, Mapping[str, object]]],
    reference: str,
    seeds: Sequence[int],
    unit: PositionUnit,
) -> tuple[str, str]:
    """The seed table as Markdown (with its footnote) and as CSV, in `unit`'s terms."""
    header, rows = relabel_table(*seed_rows(table, reference), unit)
    measured = any("uncertainty" in stats for rows in table.values() for stats in rows.values())
    footnote = seed_footnote(seeds, unit.metric, uncertainty=measured)
    return as_markdown(header, rows) + footnote, as_csv(header, rows)


def write_seed_comparison(
    results: SeedResults,
    floors: Mapping[str, MethodResult],
    reference: str,
    run_dir: Path,
    bootstrap_seed: int = 0,
    unit: PositionUnit = METRES,
    splits: Mapping[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """comparison.md / .csv / .json at the top of the run: the spread over training seeds
    and each method's paired test against `reference` (printed too).

    With `splits` (scene -> split record), comparison.json holds them as `splits` and
    comparison.md says them in one line per scene.

    Returns:
        What comparison.json holds (keys in `unit`'s terms).
    """
    run_dir = Path(run_dir)
    splits = splits or {}
    seeds = sorted(results)
    table = seed_comparison(results, floors, reference, bootstrap_seed)
    markdown, csv_text = seed_tables(table, reference, seeds, unit)
    write_text_atomic(text_note(unit) + split_lines(splits) + markdown, run_dir / "comparison.md")
    write_text_atomic(csv_text, run_dir / "comparison.csv")
    scenes = {
        scene: {method: relabel_tree(stats, unit) for method, stats in by_method.items()}
        for scene, by_method in table.items()
    }
    report = {**json_note(unit), "reference": reference, "seeds": seeds, "scenes": scenes}
    if splits:
        report["splits"] = dict(splits)
    write_text_atomic(strict_json(report), run_dir / "comparison.json")
    print(f"\nOver training seeds {seeds} (each seed's tables and figures: seed_<n>/)\n")
    print(split_lines(splits) + markdown)
    print(f"comparison over seeds: {run_dir / 'comparison.md'}")
    return report


def split_lines(splits: Mapping[str, dict[str, Any]]) -> str:
    """Each scene's sequences and reference, one line each, above a Markdown table
    ("" without records)."""
    if not splits:
        return ""
    named = len(splits) > 1
    lines = [split_line(record, scene if named else None) for scene, record in splits.items()]
    return "\n".join(lines) + "\n\n"
