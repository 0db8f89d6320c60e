"""One query at a time, this tree against an earlier revision: did a rewrite cost speed?

Issue 21 replaced the threaded lockstep scheduler with ask/tell searches driven by one
loop; this measures whether `Relocalizer.localize` got slower for it. It extracts the
earlier revision (`git archive`, default: the last commit before the rewrite), renders
the paper's geometry once (640 x 480 synthetic views; map and queries shared by both
trees), then runs benchmarks/revision_child.py in each tree in turn, `--repeats` times
(round robin, so a slow moment of the machine does not land on one tree). Each run
builds a seeded, untrained 224-pixel PoseNet and a k-means map, warms up on one query,
and times every query one at a time for each setting. Reports each tree's median
ms/query, the ratio, and whether both trees chose the same crops. Prints a table,
writes JSON.

    .venv/bin/python benchmarks/revision_throughput.py --queries 32 --map-images 20
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import render_views, write_json  # benchmarks/, the script's own folder
from revision_child import SETTINGS

HERE = Path(__file__).resolve().parent
BEFORE_ASK_TELL = "d33bfb7"  # recorded answers, the commit before the ask/tell rewrite


def extract(revision: str, into: Path) -> Path:
    """The source tree of `revision` of this repository, unpacked under `into`."""
    archive = subprocess.run(
        ["git", "-C", str(HERE.parent), "archive", revision, "relocfw", "plugins", "conf"],
        check=True,
        capture_output=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def timing_run(tree: Path, data: Path, args: argparse.Namespace, out: Path) -> dict:
    command = [sys.executable, str(HERE / "revision_child.py"), "--tree", str(tree)]
    command += ["--data", str(data), "--batch-size", str(args.batch_size), "--out", str(out)]
    subprocess.run([*command, "--only", *args.only], check=True)
    return json.loads(out.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", default=BEFORE_ASK_TELL, help="the earlier revision")
    parser.add_argument("--queries", type=int, default=32, help="test-lap views")
    parser.add_argument("--map-images", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=16, help="most windows per pass")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each tree")
    parser.add_argument("--only", nargs="+", choices=sorted(SETTINGS), default=list(SETTINGS))
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/revision_throughput.json")
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        queries, _ = render_views(args.queries, -1)
        map_images, _ = render_views(args.map_images, 0)
        data = scratch / "views.npz"
        np.savez(data, queries=np.stack(queries), map_images=np.stack(map_images))
        trees = {args.against: extract(args.against, Path(tempfile.mkdtemp(dir=scratch)))}
        trees["this tree"] = HERE.parent
        runs: dict[str, list[dict]] = {name: [] for name in trees}
        for repeat in range(args.repeats):
            for name, tree in trees.items():  # the trees take turns
                print(f"repeat {repeat + 1}/{args.repeats}: {name}", flush=True)
                runs[name].append(timing_run(tree, data, args, scratch / "run.json"))
    before, after = (runs[name] for name in trees)
    rows = []
    for setting in args.only:
        ms = {
            name: float(np.median([r[setting]["seconds"] for r in tree_runs])) * 1000 / args.queries
            for name, tree_runs in runs.items()
        }
        crops = zip(before[0][setting]["crops"], after[0][setting]["crops"], strict=True)
        same = np.mean([a == b for a, b in crops])
        rows.append(
            {
                "setting": setting,
                "before_ms_per_query": ms[args.against],
                "this_tree_ms_per_query": ms["this tree"],
                "this_over_before": ms["this tree"] / ms[args.against],
                "before_seconds": [r[setting]["seconds"] for r in before],
                "this_tree_seconds": [r[setting]["seconds"] for r in after],
                "same_crop": float(same),
            }
        )
        r = rows[-1]
        print(
            f"{setting:<12} {args.against} {r['before_ms_per_query']:8.1f} ms/query, "
            f"this tree {r['this_tree_ms_per_query']:8.1f} ms/query "
            f"(x{r['this_over_before']:.2f}); same crop {r['same_crop']:.0%}"
        )
    report = {
        "against": args.against,
        "queries": args.queries,
        "map_images": args.map_images,
        "batch_size": args.batch_size,
        "repeats": args.repeats,
        "torch_threads": after[0]["torch_threads"],
        "machine": platform.machine(),
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
