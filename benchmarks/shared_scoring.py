"""scoring=shared against scoring=plain with a trained model: exactness and accuracy.

Loads a model file written by `relocfw` (task=relocalize) and the test split of the
dataset it was built on, then for every test image:

- descriptor difference: for every window the sweep scores, the shared descriptor
  against the plain one (relative L2), and whether both rank the same window first;
- pose difference: the answers of GA with shared scoring against GA with plain
  scoring (the pose itself always comes from the plain path, so they differ only
  where the two choose different crops);
- accuracy: median errors of plain and shared GA over several GA seeds (the seed-to-
  seed spread is the noise the two are compared within), and of the sweep.

Prints a table, writes JSON.

    relocfw quiet=true hydra.run.dir=outputs/demo       # writes outputs/demo/model.relocfw
    .venv/bin/python benchmarks/shared_scoring.py --model outputs/demo/model.relocfw \\
        --out benchmarks/results/shared_scoring.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from common import (  # benchmarks/, the script's own folder
    DEFAULT_CACHE,
    model_frames,
    with_search,
    write_json,
)

from relocfw import Relocalizer, load_model
from relocfw.core.geometry import orientation_error_deg, position_error
from relocfw.core.interfaces import crop_at, crop_side_and_span
from relocfw.core.values import Pose
from relocfw.data.frames import read_images
from relocfw.plugins.ga_crop import GeneticCropSearch
from relocfw.plugins.sweep_crop import SweepCrop


def descriptor_agreement(plain: Relocalizer, shared: Relocalizer, image: np.ndarray) -> dict:
    """Shared vs plain descriptors of every distinct sweep window of one image.

    The strip and its windows are the pipeline's own (the model's crop_scale
    included), one window per distinct crop offset, each scored through the
    pipeline's Scorer: plainly, and pooled from the strip's maps as scoring=shared
    pools them (relocfw.core.scorer.Scorer.shared), both looked up in the same map.
    """
    strip = plain.scorer.strip(image)
    _, span = crop_side_and_span(strip.width, strip.height)
    windows = (strip.window(crop_at(o, strip.width, strip.height)) for o in range(span + 1))
    corners = list(dict.fromkeys(windows))
    exact = plain.scorer.forward(torch.stack([strip.cut(c) for c in corners])).features
    maps = shared.scorer.strip_maps(strip)
    with torch.inference_mode():  # the descriptors Scorer.shared looks up in the map
        pooled = shared.backbone.describe_pooled(maps.pooled(corners))
    approximate = pooled.double().cpu().numpy()
    relative = np.linalg.norm(approximate - exact, axis=1) / np.linalg.norm(exact, axis=1)
    exact_distance = plain.scorer.map_distance(exact)
    approximate_distance = plain.scorer.map_distance(approximate)
    picked = int(np.argmin(approximate_distance))
    return {
        "relative_l2": relative,
        "same_best": picked == int(np.argmin(exact_distance)),
        # What choosing by the shared score costs, measured in plain distance.
        "regret": float(exact_distance[picked] - exact_distance.min()),
    }


def errors(answers: list, frames: list) -> tuple[np.ndarray, np.ndarray]:
    return pose_difference([a.pose for a in answers], [f.pose for f in frames])


def pose_difference(a: list[Pose], b: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (deg) between paired poses."""
    positions = position_error(np.stack([p.position for p in a]), np.stack([p.position for p in b]))
    angles = orientation_error_deg(
        np.stack([p.quaternion for p in a]), np.stack([p.quaternion for p in b])
    )
    return positions, angles


def bootstrap_median_difference(
    a: np.ndarray, b: np.ndarray, rng: np.random.Generator, draws: int = 2000
) -> list[float]:
    """95% interval of median(a) - median(b) over query resamples (paired)."""
    picks = rng.integers(0, len(a), size=(draws, len(a)))
    differences = np.median(a[picks], axis=1) - np.median(b[picks], axis=1)
    return [float(v) for v in np.percentile(differences, [2.5, 97.5])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--seeds", type=int, default=5, help="GA seeds per scoring")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/shared_scoring.json"))
    args = parser.parse_args()
    plain = load_model(args.model)
    shared = load_model(args.model, overrides={"scoring": "shared"})
    frames = model_frames(plain, args.cache.expanduser())
    images = read_images(frames, quiet=True)

    agreement = [descriptor_agreement(plain, shared, image) for image in images]
    relative = np.concatenate([a["relative_l2"] for a in agreement])
    rows, answers = [], {}
    for search, seeds in (("ga", range(args.seeds)), ("sweep", [None])):
        for scoring, loaded in (("plain", plain), ("shared", shared)):
            for seed in seeds:
                crop = SweepCrop() if seed is None else GeneticCropSearch(seed=seed)
                relocalizer = with_search(loaded, crop)
                found = [relocalizer.localize(image) for image in images]
                answers[search, scoring, seed] = found
                position, angle = errors(found, frames)
                rows.append(
                    {
                        "search": search,
                        "scoring": scoring,
                        "seed": seed,
                        "median_position_m": float(np.median(position)),
                        "median_orientation_deg": float(np.median(angle)),
                        "mean_position_m": float(np.mean(position)),
                        "ms_per_query": 1000 * float(np.mean([a.seconds for a in found])),
                        "crops_per_query": float(np.mean([a.evaluations for a in found])),
                        "passes_per_query": float(np.mean([a.network_passes for a in found])),
                    }
                )
    plain_ga = [a for seed in range(args.seeds) for a in answers["ga", "plain", seed]]
    shared_ga = [a for seed in range(args.seeds) for a in answers["ga", "shared", seed]]
    differences = np.stack(
        pose_difference([a.pose for a in plain_ga], [a.pose for a in shared_ga]), axis=1
    )
    same_crop = np.mean([p.crop == s.crop for p, s in zip(plain_ga, shared_ga, strict=True)])
    # The same comparison between two plain runs that differ only in the GA's seed:
    # how far apart answers are when nothing but the search's randomness changes.
    plain_next = [
        a for seed in range(args.seeds) for a in answers["ga", "plain", (seed + 1) % args.seeds]
    ]
    seed_differences = np.stack(
        pose_difference([a.pose for a in plain_ga], [a.pose for a in plain_next]), axis=1
    )

    def ga_medians(scoring: str) -> list[float]:
        return [
            r["median_position_m"] for r in rows if r["search"] == "ga" and r["scoring"] == scoring
        ]

    rng = np.random.default_rng(0)
    plain_seed0 = errors(answers["ga", "plain", 0], frames)[0]
    shared_seed0 = errors(answers["ga", "shared", 0], frames)[0]
    report = {
        "model": str(args.model),
        "test_images": len(images),
        "descriptor_relative_l2": {
            "median": float(np.median(relative)),
            "p95": float(np.percentile(relative, 95)),
            "max": float(relative.max()),
        },
        "sweep_same_best_window": float(np.mean([a["same_best"] for a in agreement])),
        "sweep_median_regret": float(np.median([a["regret"] for a in agreement])),
        "ga_same_crop": float(same_crop),
        "ga_pose_difference": {
            "median_m": float(np.median(differences[:, 0])),
            "max_m": float(differences[:, 0].max()),
            "median_deg": float(np.median(differences[:, 1])),
            "max_deg": float(differences[:, 1].max()),
        },
        "ga_plain_seed_to_seed_pose_difference": {
            "median_m": float(np.median(seed_differences[:, 0])),
            "median_deg": float(np.median(seed_differences[:, 1])),
        },
        "ga_median_position_by_seed": {
            "plain": ga_medians("plain"),
            "shared": ga_medians("shared"),
        },
        "ga_seed0_median_difference_95ci_m": bootstrap_median_difference(
            shared_seed0, plain_seed0, rng
        ),
        "rows": rows,
    }
    print(f"{'search':<6} {'scoring':<7} {'seed':>4} {'med m':>7} {'med deg':>8} {'ms':>7}")
    for r in rows:
        seed = "" if r["seed"] is None else r["seed"]
        print(
            f"{r['search']:<6} {r['scoring']:<7} {seed!s:>4} {r['median_position_m']:>7.3f} "
            f"{r['median_orientation_deg']:>8.2f} {r['ms_per_query']:>7.1f}"
        )
    d = report["descriptor_relative_l2"]
    print(
        f"descriptor relative L2, shared vs plain: median {d['median']:.3f}, "
        f"p95 {d['p95']:.3f}, max {d['max']:.3f}"
    )
    print(
        f"sweep picks the same window: {report['sweep_same_best_window']:.0%}; "
        f"GA same crop: {same_crop:.0%}; GA pose difference median "
        f"{report['ga_pose_difference']['median_m']:.3f} m / "
        f"{report['ga_pose_difference']['median_deg']:.2f} deg"
    )
    seeds = report["ga_plain_seed_to_seed_pose_difference"]
    print(
        f"for scale, plain GA against plain GA with the next seed: median "
        f"{seeds['median_m']:.3f} m / {seeds['median_deg']:.2f} deg"
    )
    low, high = report["ga_seed0_median_difference_95ci_m"]
    print(f"GA median position, shared - plain (seed 0), 95% CI: [{low:+.3f}, {high:+.3f}] m")
    write_json(report, args.out)


if __name__ == "__main__":
    main()
