"""Which training crops teach PoseNet better: relocfw's or PoseNet's (train.crop_scale).

crop_scale 1.0 cuts a random square of the whole short side (it moves along the long
axis only, as the crops of the query do); crop_scale 1.142857 is PoseNet's scheme (a
random 224 crop of the image scaled to a 256-pixel short side: it moves in both axes).
Each setting trains the demo preset's model per seed through the CLI and answers with
the centre crop (PoseNet). Settings are chosen on VALIDATION splits carved from the
training data (never the test split):

- synthetic: train on training laps 1-2, validate on lap 3 (the rendered scene's own
  7-Scenes folder read with dataset=sevenscenes);
- redkitchen: train on sequences 1, 5, 7, validate on sequence 3 (needs
  ../shared/data/7scenes-redkitchen).

`--split test` runs the usual train/test splits instead, to report the chosen default.
Test time matches training: a crop_scale model sees the central 1/crop_scale of each
query crop, as PoseNet tests on the centre 224 of the 256-pixel image. Prints each
scheme's medians (mean +- std over seeds) and a paired per-query test between the
schemes (Wilcoxon signed-rank, bootstrap 95% interval of the difference of medians);
writes JSON.

    .venv/bin/python benchmarks/training_crops.py --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import DEFAULT_CACHE, synthetic_validation, write_json  # benchmarks/, own folder
from scipy.stats import wilcoxon

SCALES = {"relocfw (1.0)": 1.0, "posenet (256/224)": 256 / 224}
REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen"


def dataset_overrides(name: str, split: str, cache_dir: Path) -> list[str]:
    if name == "synthetic":
        if split == "test":
            return []
        return synthetic_validation(cache_dir)
    overrides = ["dataset=sevenscenes", f"dataset.root={REDKITCHEN}", "dataset.scene=redkitchen"]
    if split == "validation":
        overrides += ["dataset.train_sequences=[1,5,7]", "dataset.test_sequences=[3]"]
    return overrides


def run(overrides: list[str], out: Path) -> tuple[dict, dict[str, list[float]]]:
    command = [
        sys.executable,
        "-m",
        "relocfw",
        "crop=centre",
        "index=exhaustive",
        "baselines=[mean_pose]",
        "quiet=true",
        f"hydra.run.dir={out}",
        *overrides,
    ]
    print("$", " ".join(command), flush=True)
    subprocess.run(command, check=True, env=os.environ.copy())
    rows = json.loads((out / "summary.json").read_text())
    with open(out / "results.csv") as stream:
        answers = [r for r in csv.DictReader(stream) if r["method"] == rows[-1]["method"]]
    errors = {
        "frames": [r["frame"] for r in answers],
        "position_m": [float(r["position_error_m"]) for r in answers],
        "orientation_deg": [float(r["orientation_error_deg"]) for r in answers],
    }
    return rows[-1], errors


def paired(first: list[dict], second: list[dict], key: str, rng: np.random.Generator) -> dict:
    """Paired comparison of per-query errors (same seed, same query) of two schemes.

    Wilcoxon signed-rank test on the differences, and a bootstrap 95% interval of the
    difference of medians (second - first), resampling queries within each seed.
    """
    a = np.concatenate([r["errors"][key] for r in first])
    b = np.concatenate([r["errors"][key] for r in second])
    test = wilcoxon(b, a)
    for x, y in zip(first, second, strict=True):
        if x["seed"] != y["seed"] or x["errors"]["frames"] != y["errors"]["frames"]:
            raise SystemExit(f"error: runs do not pair up (seed {x['seed']} / {y['seed']})")
    groups = [
        (np.array(x["errors"][key]), np.array(y["errors"][key]))
        for x, y in zip(first, second, strict=True)
    ]
    boots = []
    for _ in range(2000):
        picks = [rng.integers(0, len(x), len(x)) for x, _ in groups]
        xa = np.concatenate([x[p] for (x, _), p in zip(groups, picks, strict=True)])
        xb = np.concatenate([y[p] for (_, y), p in zip(groups, picks, strict=True)])
        boots.append(np.median(xb) - np.median(xa))
    low, high = np.percentile(boots, [2.5, 97.5])
    return {
        "pairs": int(len(a)),
        "median_difference": float(np.median(b) - np.median(a)),
        "bootstrap_95": [float(low), float(high)],
        "wilcoxon_p": float(test.pvalue),
        "second_better_share": float(np.mean(b < a)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--datasets", nargs="+", default=["synthetic", "redkitchen"])
    parser.add_argument("--split", choices=("validation", "test"), default="validation")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(f"benchmarks/results/training_crops_{args.split}.json")
    cache_dir = DEFAULT_CACHE.expanduser()
    if "redkitchen" in args.datasets and not REDKITCHEN.is_dir():
        sys.exit(f"error: Red Kitchen frames not found at {REDKITCHEN}")
    runs = []
    with tempfile.TemporaryDirectory() as scratch:
        for dataset in args.datasets:
            for label, scale in SCALES.items():
                for seed in args.seeds:
                    overrides = dataset_overrides(dataset, args.split, cache_dir)
                    overrides += [f"train.crop_scale={scale:.6f}", f"seed={seed}"]
                    run_dir = Path(scratch) / f"{dataset}-{scale:.3f}-{seed}"
                    summary, errors = run(overrides, run_dir)
                    runs.append(
                        {
                            "dataset": dataset,
                            "scheme": label,
                            "seed": seed,
                            **summary,
                            "errors": errors,
                        }
                    )
    print(f"\n{args.split} split, centre crop, demo preset; mean +- std over seeds {args.seeds}")
    print(f"{'dataset':<12} {'scheme':<20} {'med pos (m)':>16} {'med ori (deg)':>16}")
    table = []
    for dataset in args.datasets:
        for label in SCALES:
            mine = [r for r in runs if r["dataset"] == dataset and r["scheme"] == label]
            pos = np.array([r["median_position_m"] for r in mine])
            ori = np.array([r["median_orientation_deg"] for r in mine])
            table.append(
                {
                    "dataset": dataset,
                    "scheme": label,
                    "median_position_m_mean": float(pos.mean()),
                    "median_position_m_std": float(pos.std(ddof=1)) if len(pos) > 1 else 0.0,
                    "median_orientation_deg_mean": float(ori.mean()),
                    "median_orientation_deg_std": float(ori.std(ddof=1)) if len(ori) > 1 else 0.0,
                }
            )
            row = table[-1]
            print(
                f"{dataset:<12} {label:<20} "
                f"{row['median_position_m_mean']:>8.3f} +- {row['median_position_m_std']:.3f} "
                f"{row['median_orientation_deg_mean']:>8.2f} +- "
                f"{row['median_orientation_deg_std']:.2f}"
            )
    rng = np.random.default_rng(0)
    tests = {}
    first, second = SCALES
    print(f"\npaired per-query test, {second} - {first} (same seed, same query)")
    for dataset in args.datasets:
        mine = {
            label: sorted(
                (r for r in runs if r["dataset"] == dataset and r["scheme"] == label),
                key=lambda r: r["seed"],
            )
            for label in SCALES
        }
        tests[dataset] = {
            key: paired(mine[first], mine[second], key, rng)
            for key in ("position_m", "orientation_deg")
        }
        for key, result in tests[dataset].items():
            low, high = result["bootstrap_95"]
            print(
                f"{dataset:<12} {key:<16} median difference {result['median_difference']:+.3f} "
                f"[{low:+.3f}, {high:+.3f}], Wilcoxon p = {result['wilcoxon_p']:.2g}, "
                f"{second} better on {result['second_better_share']:.0%} of pairs"
            )
    report = {"split": args.split, "seeds": args.seeds, "table": table, "paired": tests}
    write_json({**report, "runs": runs}, out)


if __name__ == "__main__":
    main()
