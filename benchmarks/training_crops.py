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
Prints a table, writes JSON.

    .venv/bin/python benchmarks/training_crops.py --seeds 0 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

from relocfw.data.synthetic import SyntheticSceneSpec, ensure_synthetic_scene

SCALES = {"relocfw (1.0)": 1.0, "posenet (256/224)": 256 / 224}
REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen"


def dataset_overrides(name: str, split: str, cache_dir: Path) -> list[str]:
    if name == "synthetic":
        if split == "test":
            return []
        folder = ensure_synthetic_scene(SyntheticSceneSpec(), cache_dir, quiet=True)
        return [
            "dataset=sevenscenes",
            f"dataset.root={folder}",
            "dataset.scene=null",
            "dataset.train_sequences=[1,2]",
            "dataset.test_sequences=[3]",
        ]
    overrides = ["dataset=sevenscenes", f"dataset.root={REDKITCHEN}", "dataset.scene=redkitchen"]
    if split == "validation":
        overrides += ["dataset.train_sequences=[1,5,7]", "dataset.test_sequences=[3]"]
    return overrides


def run(overrides: list[str], out: Path) -> dict:
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
    return rows[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--datasets", nargs="+", default=["synthetic", "redkitchen"])
    parser.add_argument("--split", choices=("validation", "test"), default="validation")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(f"benchmarks/results/training_crops_{args.split}.json")
    cache_dir = Path(os.environ.get("RELOCFW_CACHE", "~/.cache/relocfw")).expanduser()
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
                    summary = run(overrides, run_dir)
                    runs.append({"dataset": dataset, "scheme": label, "seed": seed, **summary})
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
    write_json({"split": args.split, "seeds": args.seeds, "table": table, "runs": runs}, out)


if __name__ == "__main__":
    main()
