"""What each family costs to build and to ship: the network's training, the map's or
head's fit, and the model file's bytes, for every row of a methods file (--methods,
default conf/methods/families.yaml; docs/results/families.md).

Each row is composed as `relocfw task=compare methods=families` composes it (the
command line's overrides, then the row's), built with relocfw's own CLI functions
(method_rows, build_method, prepare_model, on_engine, fit_method) on the map images, in an empty
cache folder, so nothing comes from an earlier run: the first row on a network
trains it, and later rows on the same network find it in this run's cache (their
network seconds are then the load's, and the table says which row trained it).
A refiner's fit (a structure map, a scene-coordinate head, an LSTM) is never
shared: each row's refiner options differ. The model file is the one
`relocfw task=relocalize` writes (save_model), in a temporary folder; its bytes are
what a robot carries (a refiner that cannot be stored is said so).

Queries are not timed here: ms per query come from the round-robin compare run.
Run it on an otherwise idle machine; the JSON is written after every row, so a run
cut short keeps what it measured.

    RK="dataset=sevenscenes dataset.root=../shared/data/7scenes-redkitchen dataset.scene=redkitchen"
    .venv/bin/python benchmarks/family_costs.py --out benchmarks/results/family_costs.json \\
        -- $RK preset=real_cpu_quick seed=0
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import write_json  # benchmarks/, the script's own folder
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from relocfw.app.engines import on_engine
from relocfw.app.methods import build, build_method
from relocfw.app.results import fit_method
from relocfw.app.splits import load_split
from relocfw.app.tasks.compare import method_rows
from relocfw.app.training_runs import prepare_model
from relocfw.app.validation_block import carve_validation
from relocfw.model.model_file import save_model, stores_refiner

FAMILIES = Path(__file__).resolve().parents[1] / "conf" / "methods" / "families.yaml"


def family_rows(path: Path) -> dict[str, list[str]]:
    """The methods file's rows, name -> overrides, read and checked as task=compare
    reads compare.methods (old spellings rewritten)."""
    return method_rows(OmegaConf.create({"compare": {"methods": OmegaConf.load(path)}}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/family_costs.json"))
    parser.add_argument("--methods", type=Path, default=FAMILIES)
    parser.add_argument("--rows", nargs="*", help="only these rows (default: every row)")
    parser.add_argument("overrides", nargs="*", help="relocfw overrides for every row")
    args = parser.parse_args()
    rows = family_rows(args.methods)
    unknown = sorted(set(args.rows or ()) - set(rows))
    if unknown:
        sys.exit(f"--rows: {', '.join(unknown)} not in {args.methods}")
    chosen = {n: o for n, o in rows.items() if not args.rows or n in args.rows}
    device = torch.device("cpu")
    report = {
        "command": " ".join(sys.argv),
        "machine": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "overrides": args.overrides,
        "rows": {},
        "complete": False,
    }
    trained_by: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="family_costs_") as scratch:
        cache = Path(scratch) / "cache"
        base = [*args.overrides, f"cache_dir={cache}", "quiet=true"]
        with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
            first = compose("config", overrides=base, return_hydra_config=True)
            choices = first.hydra.runtime.choices
            dataset = build(first, "dataset", choices["dataset"])
            train = load_split(dataset, "train", quiet=True)
            train, _ = carve_validation(first, train)
            report["map_images"] = len(train[0])
            for name, overrides in chosen.items():
                cfg = compose("config", overrides=base + overrides, return_hydra_config=True)
                method = build_method(cfg, cfg.hydra.runtime.choices, label=name)
                started = time.perf_counter()
                checkpoint = prepare_model(cfg, method, train, device)
                trained = time.perf_counter()
                relocalizer = on_engine(
                    cfg, method.relocalizer(device), checkpoint, device, train[1]
                )
                engined = time.perf_counter()
                fit_method(name, relocalizer, train, quiet=True)
                fitted = time.perf_counter()
                model = save_model(
                    Path(scratch) / "model.relocfw",
                    relocalizer,
                    method.part_options,
                    {"method": name, "map_images": len(train[0])},
                )
                row = {
                    "network_seconds": trained - started,
                    "network_trained_by": trained_by.setdefault(checkpoint.name, name),
                    "engine_seconds": engined - trained,
                    "fit_seconds": fitted - engined,
                    "model_bytes": model.stat().st_size,
                    "refiner_stored": method.refiner is None or stores_refiner(relocalizer),
                }
                parts = getattr(relocalizer.refiner, "fit_seconds", None)
                if parts:  # e.g. scene coordinates: the buffer's and the head's share
                    row["fit_parts_seconds"] = dict(parts)
                report["rows"][name] = row
                print(
                    f"{name}: network {row['network_seconds']:.1f} s "
                    f"(trained by {row['network_trained_by']}), fit {row['fit_seconds']:.1f} s, "
                    f"model file {row['model_bytes'] / 1e6:.2f} MB",
                    flush=True,
                )
                write_json(report, args.out)
                model.unlink()
    report["complete"] = True
    write_json(report, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
