"""Paired tests between rows of two `task=compare` runs on the same queries and seeds.

A compare run pairs its own rows; this pairs a row of one run with a row of another
(today's code against a change, both with the same trained models), from the per-seed
results CSVs the runs wrote (`seed_N/results_<scene>.csv`; a run of one seed keeps
`results_<scene>.csv` in its own folder, and pairs with another run of one seed). The
seeds are those both runs have; a query missing from either side, or in another
order, is an error, not a silently shorter test.

    python benchmarks/paired_runs.py --out benchmarks/results/x.json \
        NEW_RUN:"Structure RGB-only"=OLD_RUN:"Structure RGB-only" ...
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from relocfw.core.atomic_files import write_text_atomic
from relocfw.core.errors import DataError
from relocfw.report.statistics import paired_test

ERRORS = {"position_m": "position_error_m", "orientation_deg": "orientation_error_deg"}
WITHIN = (0.05, 5.0)  # the 5 cm / 5 deg share reported beside the test
# What a row cost, per seed, from the run's summary_<scene>.json (stored beside the
# errors so the ms a report cites are in the JSON too): the median ms per query, and
# a refiner's median ms per part and median confidence where it reports them.
COST_PREFIXES = ("refine_median_ms_", "refine_median_confidence")


# The "seed" of a run of one training seed, whose results lie in the run's own folder.
ONE_SEED = -1


def run_seeds(run: Path) -> set[int]:
    """The training seeds a compare run holds results for ({ONE_SEED} for a run of one
    seed)."""
    if not run.is_dir():
        raise DataError(f"{run}: not a compare run folder")
    seeds = {int(path.name.split("_")[1]) for path in run.glob("seed_*") if path.is_dir()}
    if not seeds and any(run.glob("results_*.csv")):
        return {ONE_SEED}
    return seeds


def seed_folder(run: Path, seed: int) -> Path:
    return run if seed == ONE_SEED else run / f"seed_{seed}"


def row_results(run: Path, seed: int, method: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Frames, [N, 2] errors and the fell-back flags of one row of one seed."""
    folder = seed_folder(run, seed)
    files = sorted(folder.glob("results_*.csv"))
    if len(files) != 1:
        raise DataError(f"{folder}: expected one results_*.csv, found {len(files)}")
    frames, errors, fell_back = [], [], []
    with files[0].open(newline="") as handle:
        for record in csv.DictReader(handle):
            if record["method"] != method:
                continue
            frames.append(record["frame"])
            errors.append([float(record[key]) for key in ERRORS.values()])
            fell_back.append(record.get("fell_back", "0") not in ("0", "", "nan"))
    if not frames:
        raise DataError(f"{files[0]}: no rows of method {method!r}")
    return frames, np.array(errors), np.array(fell_back)


def row_costs(run: Path, seed: int, method: str) -> dict[str, float]:
    """One row's median ms per query (and its refiner's parts) in one seed, from the
    run's summary JSON; {} where the run wrote none (a folder of an older run)."""
    files = sorted(seed_folder(run, seed).glob("summary_*.json"))
    if len(files) != 1:
        return {}
    for record in json.loads(files[0].read_text()):
        if record.get("method") == method:
            costs = {"median_ms": 1000.0 * float(record["median_seconds_per_query"])}
            for key, value in record.items():
                if key.startswith(COST_PREFIXES) and value not in (None, ""):
                    costs[key] = float(value)
            return costs
    return {}


def costs_over_seeds(run: Path, method: str, seeds: list[int]) -> dict[str, list[float]]:
    """row_costs per seed, as lists in seed order (keys every seed reports)."""
    per_seed = [row_costs(run, seed, method) for seed in seeds]
    keys = set.intersection(*(set(costs) for costs in per_seed)) if per_seed else set()
    return {key: [round(costs[key], 2) for costs in per_seed] for key in sorted(keys)}


def side(run: Path, method: str, seeds: list[int]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """[S, N, 2] errors and [S, N] fell-back flags of a row over seeds (same frames)."""
    frames, errors, flags = None, [], []
    for seed in seeds:
        names, seed_errors, seed_flags = row_results(run, seed, method)
        if frames is not None and names != frames:
            raise DataError(f"{run}: method {method!r} answered other frames in seed {seed}")
        frames = names
        errors.append(seed_errors)
        flags.append(seed_flags)
    return frames, np.stack(errors), np.stack(flags)


def summary(errors: np.ndarray, flags: np.ndarray) -> dict[str, object]:
    """Per-seed medians, the share within 5 cm / 5 deg and fallbacks of one row."""
    within = (errors[..., 0] <= WITHIN[0]) & (errors[..., 1] <= WITHIN[1])
    return {
        "median_position_m": np.median(errors[..., 0], axis=1).round(4).tolist(),
        "median_orientation_deg": np.median(errors[..., 1], axis=1).round(3).tolist(),
        "within_5cm_5deg": within.mean(axis=1).round(4).tolist(),
        "fell_back": flags.sum(axis=1).astype(int).tolist(),
        "queries": int(errors.shape[1]),
    }


def compare_pair(new: tuple[Path, str], old: tuple[Path, str]) -> dict[str, object]:
    """The paired test of row `new` against row `old` over the seeds both runs hold."""
    seeds = sorted(run_seeds(new[0]) & run_seeds(old[0]))
    if not seeds:
        raise DataError(f"{new[0]} and {old[0]} share no training seed")
    new_frames, new_errors, new_flags = side(*new, seeds)
    old_frames, old_errors, old_flags = side(*old, seeds)
    if new_frames != old_frames:
        raise DataError(f"{new[0]} and {old[0]}: the two rows answered different queries")
    splits = {"new": run_split(new[0]), "old": run_split(old[0])}
    check_same_scoring(new[0], old[0], splits["new"], splits["old"])
    result: dict[str, object] = {
        "seeds": seeds,
        "splits": splits,
        "new": {
            "run": str(new[0]),
            "method": new[1],
            **summary(new_errors, new_flags),
            "costs": costs_over_seeds(*new, seeds),
        },
        "old": {
            "run": str(old[0]),
            "method": old[1],
            **summary(old_errors, old_flags),
            "costs": costs_over_seeds(*old, seeds),
        },
    }
    for number, kind in enumerate(ERRORS):
        result[kind] = paired_test(new_errors[..., number], old_errors[..., number], seed=0)
    return result


def run_split(run: Path) -> dict | None:
    """The split record (relocfw.app.split_record) of a compare run's one scene, from
    its comparison.json; None for a run written before runs recorded it."""
    path = run / "comparison.json"
    if not path.is_file():
        return None
    splits = json.loads(path.read_text()).get("splits") or {}
    return next(iter(splits.values()), None) if len(splits) == 1 else None


def check_same_scoring(new_run: Path, old_run: Path, new: dict | None, old: dict | None) -> None:
    """Refuse a pair whose runs tested other sequences or scored against another pose
    reference (the same frame names then carry other truths): a paired test needs one
    truth per query. Runs without a record are paired as before."""
    if new is None or old is None:
        return
    for key in ("test_sequences",):
        if new[key] != old[key]:
            raise DataError(f"{new_run} and {old_run}: {key} {new[key]} against {old[key]}")
    mine, theirs = new["pose_reference"], old["pose_reference"]
    if (mine["kind"], mine.get("sha256")) != (theirs["kind"], theirs.get("sha256")):
        raise DataError(
            f"{new_run} and {old_run} score against other pose references "
            f"({mine['kind']} {mine.get('file')} against {theirs['kind']} {theirs.get('file')})"
        )


def parsed_side(text: str) -> tuple[Path, str]:
    """RUN:METHOD, split at the first colon."""
    run, colon, method = text.partition(":")
    if not colon or not method:
        raise argparse.ArgumentTypeError(f"expected RUN:METHOD, got {text!r}")
    return Path(run), method


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("pairs", nargs="+", help="NEW_RUN:METHOD=OLD_RUN:METHOD (quote names)")
    parser.add_argument("--out", type=Path, required=True, help="the JSON to write")
    arguments = parser.parse_args()
    results = {}
    for pair in arguments.pairs:
        new, equals, old = pair.partition("=")
        if not equals:
            parser.error(f"expected NEW_RUN:METHOD=OLD_RUN:METHOD, got {pair!r}")
        result = compare_pair(parsed_side(new), parsed_side(old))
        results[pair] = result
        for kind in ERRORS:
            test = result[kind]
            print(
                f"{pair} {kind}: difference {test['median_difference']:+.4f} "
                f"95% {test['bootstrap_95']} p={test['wilcoxon_p']:.2g} {test['verdict']}"
            )
        print(
            "  new",
            {k: result["new"][k] for k in ("median_position_m", "within_5cm_5deg", "fell_back")},
        )
        print(
            "  old",
            {k: result["old"][k] for k in ("median_position_m", "within_5cm_5deg", "fell_back")},
        )
    write_text_atomic(json.dumps(results, indent=1, default=float) + "\n", arguments.out)


if __name__ == "__main__":
    main()
