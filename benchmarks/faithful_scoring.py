"""Fast and faithful: shared scoring whose best m candidates are re-scored plainly.

Loads a model file written by `relocfw` (task=relocalize) and the test split of the
dataset it was built on. Every query goes, in turn, through the centre crop, the
plain GA and sweep (the paper's choices), and the shared GA and sweep with
`rerank` m for each m asked. For each fast setting, against the plain search of the
same kind:

- agreement: the share of queries whose chosen window is the plain search's;
- map distance: the plain distance of the chosen crop over the plain search's
  (1: the same minimum reached; > 1: a worse crop by the paper's own objective);
- pose difference: position (m) and rotation (deg) between the two answers;
- cost: median ms/query and network passes, and ms over the centre crop's in the
  same run (queries go round robin through every setting, so a slow moment of the
  machine lands on all alike).

The plain GA with the next seed against seed 0 is the reference agreement: how often
two plain GA runs pick the same window when only the search's randomness changes.
The verdict names the cheapest setting that agrees on >= 90% of queries at <= 3x the
centre crop, or says that none does. Prints a table, writes JSON.

    relocfw dataset.width=640 dataset.height=480 backbone.input_size=224 \\
        train.batch_size=16 quiet=true hydra.run.dir=outputs/paper_geometry
    .venv/bin/python benchmarks/faithful_scoring.py \\
        --model outputs/paper_geometry/model.relocfw
"""

from __future__ import annotations

import argparse
import platform
from pathlib import Path

import numpy as np
import torch
from common import (  # benchmarks/, the script's own folder
    DEFAULT_CACHE,
    device_name,
    model_frames,
    with_search,
    write_json,
)
from shared_scoring import pose_difference

from relocfw import Relocalizer, load_model
from relocfw.data.frames import read_images
from relocfw.plugins.centre_crop import CentreCrop
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.sweep_crop import SweepCrop

AGREEMENT_NEEDED = 0.9
COST_ALLOWED = 3.0  # x the centre crop


def settings(model: Path, reranks: list[int], device: str = "cpu") -> list[tuple[str, Relocalizer]]:
    """(name, relocalizer) of every setting, each with its own loaded copy."""

    def load(crop, scoring: str = "plain", rerank: int = 1) -> Relocalizer:
        loaded = load_model(model, device, {"scoring": scoring, "rerank": rerank})
        return with_search(loaded, crop)

    rows = [
        ("centre", load(CentreCrop())),
        ("ga plain", load(GeneticCropSearch(seed=0))),
        ("ga plain, seed 1", load(GeneticCropSearch(seed=1))),
        ("sweep plain", load(SweepCrop())),
    ]
    for search, crop in (("ga", GeneticCropSearch(seed=0)), ("sweep", SweepCrop())):
        rows += [(f"{search} shared m={m}", load(crop, "shared", m)) for m in reranks]
    return rows


def compare(found: list, plain: list, images: list, relocalizer: Relocalizer) -> dict:
    """How a setting's answers stand against the plain search's, query by query."""
    strips = [relocalizer.scorer.strip(image) for image in images]
    same = [
        strip.window(a.crop) == strip.window(b.crop)
        for a, b, strip in zip(found, plain, strips, strict=True)
    ]
    ratio = np.array([a.distance / b.distance for a, b in zip(found, plain, strict=True)])
    positions, angles = pose_difference([a.pose for a in found], [b.pose for b in plain])
    return {
        "agreement": float(np.mean(same)),
        "median_distance_ratio": float(np.median(ratio)),
        "p90_distance_ratio": float(np.percentile(ratio, 90)),
        "median_pose_difference_m": float(np.median(positions)),
        "median_pose_difference_deg": float(np.median(angles)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--queries", type=int, default=0, help="first N test images; 0: all")
    parser.add_argument("--rerank", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/faithful_scoring.json")
    )
    args = parser.parse_args()
    named = settings(args.model, args.rerank, args.device)
    frames = model_frames(named[0][1], args.cache.expanduser())
    if args.queries:
        frames = frames[: args.queries]
    images = read_images(frames, quiet=True)
    for _, relocalizer in named:
        relocalizer.localize(images[0])  # warm-up: allocator, thread pools
    answers: dict[str, list] = {name: [] for name, _ in named}
    for image in images:
        for name, relocalizer in named:
            answers[name].append(relocalizer.localize(image))
    centre_ms = 1000 * float(np.median([a.seconds for a in answers["centre"]]))
    rows = []
    for name, relocalizer in named:
        found = answers[name]
        ms = 1000 * float(np.median([a.seconds for a in found]))
        row = {
            "setting": name,
            "ms_per_query": ms,
            "times_centre": ms / centre_ms,
            "network_passes": float(np.mean([a.network_passes for a in found])),
            "crops_scored": float(np.mean([a.evaluations for a in found])),
        }
        reference = "ga plain" if name.startswith("ga") else "sweep plain"
        if name != "centre" and name != reference:
            row["against"] = reference
            row.update(compare(found, answers[reference], images, relocalizer))
        rows.append(row)
    faithful = [
        r
        for r in rows
        if "shared" in r["setting"]
        and r["setting"].startswith("ga")
        and r["agreement"] >= AGREEMENT_NEEDED
        and r["times_centre"] <= COST_ALLOWED
    ]
    cheapest = min(faithful, key=lambda r: r["ms_per_query"]) if faithful else None
    verdict = (
        f"{cheapest['setting']}: agrees with the plain GA on {cheapest['agreement']:.0%} of "
        f"queries at {cheapest['times_centre']:.2f}x the centre crop"
        if cheapest
        else (
            f"no shared GA setting agrees with the plain GA on >= {AGREEMENT_NEEDED:.0%} of "
            f"queries at <= {COST_ALLOWED:g}x the centre crop"
        )
    )
    model = named[0][1]
    report = {
        "model": str(args.model),
        "input_size": int(model.backbone.input_size),
        "crop_scale": model.crop_scale,
        "image": list(images[0].shape[1::-1]),
        "queries": len(images),
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "device": device_name(args.device),
        "verdict": verdict,
        "rows": rows,
    }
    print(
        f"{'setting':<18} {'ms':>7} {'x centre':>8} {'passes':>7} {'agree':>6} "
        f"{'dist ratio':>10} {'pose diff':>15}"
    )
    for r in rows:
        agree = f"{r['agreement']:.0%}" if "agreement" in r else "-"
        ratio = f"{r['median_distance_ratio']:.3f}" if "agreement" in r else "-"
        pose = (
            f"{r['median_pose_difference_m']:.3f} m {r['median_pose_difference_deg']:.2f}"
            if "agreement" in r
            else "-"
        )
        print(
            f"{r['setting']:<18} {r['ms_per_query']:>7.1f} {r['times_centre']:>8.2f} "
            f"{r['network_passes']:>7.2f} {agree:>6} {ratio:>10} {pose:>15}"
        )
    print(f"verdict: {verdict}")
    write_json(report, args.out)


if __name__ == "__main__":
    main()
