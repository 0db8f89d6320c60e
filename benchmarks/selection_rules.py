"""Test-time selection rules against the centre crop: one (backbone, split) per command.

For each training seed, `relocfw task=diagnose` records every window of every query
twice (reusing checkpoints and recordings already in --out):
- validation: a model trained without a validation block of the training data,
  answering that block (Red Kitchen near: train on sequences 1, 5, 7, validate on 3,
  as the project's other validation studies; far: train on 1, 2, 3, validate on 4, the
  block beyond the path's end, as the far test split lies beyond it; synthetic: laps
  1-2, validate on lap 3);
- test: the model trained on all training data, answering the test split.
Then every rule's setting is chosen on the validation recordings alone, and the rules
answer the test recordings (relocfw.report.rule_study): rules.json, rules.md.

    .venv/bin/python benchmarks/selection_rules.py --scene near --seeds 0 1 2 \
        --out benchmarks/results/rules/efficientnet_near -- preset=real_cpu_quick
    .venv/bin/python benchmarks/selection_rules.py --figure benchmarks/results/rules

Everything after `--` goes to every relocfw run (the backbone and its budget).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from common import synthetic_validation  # benchmarks/, the script's folder

from relocfw.core.json_output import strict_json
from relocfw.data.synthetic import SyntheticSceneSpec
from relocfw.model.checkpoints import write_text_atomic
from relocfw.report.rule_study import as_markdown, headroom_figure, study
from relocfw.report.window_recording import load_windows

# Resolved (a linked shared/ names its real folder): the dataset root is part of a
# checkpoint's key, so models trained from the same folder by another path are reused.
SHARED = Path(__file__).resolve().parents[2] / "shared"
REDKITCHEN = (SHARED / "data" / "7scenes-redkitchen").resolve()
RK = ["dataset=sevenscenes", f"dataset.root={REDKITCHEN}", "dataset.scene=redkitchen"]
SPLITS = {
    "near": {"validation": ["[1,5,7]", "[3]"], "test": None},
    "far": {"validation": ["[1,2,3]", "[4]"], "test": ["[1,2,3,4]", "[5,6,7]"]},
}


def dataset_overrides(scene: str, part: str, cache_dir: Path) -> list[str]:
    if scene == "synthetic":
        if part == "test":
            # The rendered scene follows the run's seed (dataset.seed: ${seed}); every
            # training seed must answer the same test lap, of the scene the validation
            # laps come from (seed 0), as task=compare keeps one scene for all seeds.
            return [f"dataset.seed={SyntheticSceneSpec().seed}"]
        return synthetic_validation(cache_dir)
    sequences = SPLITS[scene][part]
    if sequences is None:
        return list(RK)
    return [
        *RK,
        f"dataset.train_sequences={sequences[0]}",
        f"dataset.test_sequences={sequences[1]}",
    ]


def recorded(scene: str, part: str, seed: int, out: Path, extra: list[str], cache: Path) -> Path:
    """The run folder of one diagnose run, run now unless its recording is there."""
    folder = out / part / f"seed_{seed}"
    if (folder / "diagnose_windows.npz").is_file():
        return folder
    command = [
        sys.executable,
        "-m",
        "relocfw",
        "task=diagnose",
        f"seed={seed}",
        "quiet=true",
        "diagnose.curve_queries=0",
        "diagnose.table3_queries=0",
        f"hydra.run.dir={folder}",
        *dataset_overrides(scene, part, cache),
        *extra,
    ]
    print("$", " ".join(command), flush=True)
    subprocess.run(command, check=True, env=os.environ.copy())
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", choices=("near", "far", "synthetic"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--title", help="the table's heading (default: the out folder's name)")
    parser.add_argument(
        "--figure", type=Path, help="draw headroom.png from every rules.json under this folder"
    )
    parser.add_argument("overrides", nargs="*", help="relocfw overrides for every run")
    args = parser.parse_args()
    if args.figure:
        reports = {
            path.parent.name: json.loads(path.read_text())
            for path in sorted(args.figure.glob("*/rules.json"))
        }
        if not reports:
            parser.error(f"no */rules.json under {args.figure}")
        print(headroom_figure(reports, args.figure / "headroom.png"))
        return
    if args.scene is None or args.out is None:
        parser.error("--scene and --out are needed (or --figure)")
    if args.scene != "synthetic" and not REDKITCHEN.is_dir():
        parser.error(f"Red Kitchen not found at {REDKITCHEN}")
    cache = Path(os.environ.get("RELOCFW_CACHE", "~/.cache/relocfw")).expanduser()
    recordings: dict[str, dict[int, list]] = {"validation": {}, "test": {}}
    for seed in args.seeds:
        for part in ("validation", "test"):
            folder = recorded(args.scene, part, seed, args.out, args.overrides, cache)
            recordings[part][seed] = load_windows(folder / "diagnose_windows.npz")
    report = study(recordings["validation"], recordings["test"])
    report["command"] = " ".join(sys.argv)
    report["relocfw_overrides"] = args.overrides
    title = args.title or args.out.name
    markdown = as_markdown(title, report)
    write_text_atomic(strict_json(report), args.out / "rules.json")
    write_text_atomic(markdown, args.out / "rules.md")
    print(markdown)


if __name__ == "__main__":
    main()
