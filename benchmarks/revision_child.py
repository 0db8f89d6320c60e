"""One timing run of benchmarks/revision_throughput.py inside one source tree.

Run by that script, not by hand: it imports relocfw from `--tree` (a checkout of any
revision since the plugins moved into relocfw.plugins), builds the paper's geometry
(seeded, untrained 224-pixel PoseNet, k-means map of the views in `--data`), and times
`Relocalizer.localize` one query at a time for each setting. It must work with both
constructors relocfw has had: keyword options (before issue 21) and `QueryOptions`.
Writes its seconds, crops and poses as JSON to `--out`.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

SETTINGS = {  # name: (crop search class in relocfw.plugins, scoring)
    "centre": ("centre_crop.CentreCrop", "plain"),
    "ga plain": ("ga_crop.GeneticCropSearch", "plain"),
    "ga shared": ("ga_crop.GeneticCropSearch", "shared"),
    "sweep plain": ("sweep_crop.SweepCrop", "plain"),
    "sweep shared": ("sweep_crop.SweepCrop", "shared"),
}


def import_tree(tree: Path) -> None:
    """Make `import relocfw` and `relocfw.plugins` come from `tree`, whatever is
    installed: the tree's top-level plugins/ folder is installed as relocfw.plugins."""
    sys.path.insert(0, str(tree))
    import relocfw

    if Path(relocfw.__file__).resolve().parent != (tree / "relocfw").resolve():
        raise SystemExit(f"relocfw imported from {relocfw.__file__}, not from {tree}")
    spec = importlib.util.spec_from_file_location(
        "relocfw.plugins",
        tree / "plugins" / "__init__.py",
        submodule_search_locations=[str(tree / "plugins")],
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["relocfw.plugins"] = module
    spec.loader.exec_module(module)


def plugin(path: str):
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(f"relocfw.plugins.{module}"), name)


def pipeline(network, index, search, scoring: str, batch_size: int):
    import relocfw

    if hasattr(relocfw, "QueryOptions"):
        options = relocfw.QueryOptions(batch_size=batch_size, scoring=scoring)
        return relocfw.Relocalizer(network, index, search, options, "cpu")
    return relocfw.Relocalizer(
        network, index, search, "cpu", batch_size=batch_size, scoring=scoring
    )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--tree", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--batch-size", type=int, required=True)
    parser.add_argument("--only", nargs="+", required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    import_tree(args.tree)
    import numpy as np
    import torch

    data = np.load(args.data)
    queries, map_images = list(data["queries"]), list(data["map_images"])
    results = {}
    for name in args.only:
        search, scoring = SETTINGS[name]
        torch.manual_seed(0)
        network = plugin("posenet.PoseNet")(input_size=224).eval()
        index = plugin("kmeans_index.KMeansIndex")(k=min(40, len(map_images)))
        relocalizer = pipeline(network, index, plugin(search)(), scoring, args.batch_size)
        relocalizer.fit(map_images)
        relocalizer.localize(queries[0])  # warm-up
        start = time.perf_counter()
        answers = [relocalizer.localize(image) for image in queries]
        seconds = time.perf_counter() - start
        results[name] = {
            "seconds": seconds,
            "crops": [[a.crop.x, a.crop.y, a.crop.size] for a in answers],
            "positions": [np.asarray(a.pose.position).tolist() for a in answers],
        }
    args.out.write_text(json.dumps({"torch_threads": torch.get_num_threads(), **results}))


if __name__ == "__main__":
    main()
